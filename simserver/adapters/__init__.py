"""Adapters between the compiled core and the outside world: the configuration files
(``config``: YAML vehicles, tires and scenes checked against the core's parameter tables;
``tir_file``: MF-Tyre .tir files; ``terrain_files`` and ``opendrive``: terrains and
roads; ``driver_config``: a car's built-in driver; ``openscenario``: the OpenSCENARIO 1.x
reader, docs/openscenario.md), the value checks every reader shares
(``validate``, core-free), run histories and plots (``history``: Parquet, the cars of a
world in one table with a ``car_id`` column; ``plots``), zenoh sessions with safe
defaults (``zenoh_io``, ``tls_front``), Rerun (``rerun_scene``, ``rerun_sink``,
``rerun_terrain``) and the live viewer (``viewer``: a separate process drawing the
published states in Rerun; ``web_viewer_host``: its web page served offline)."""
