"""The wire contract: key expressions, binary payloads and control schemas
(``protocol``), and the one table of the published state (``state_schema``). Core-free
apart from the state layout's slot names."""
