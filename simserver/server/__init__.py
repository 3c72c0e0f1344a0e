"""The live 1 kHz server: its config, command log and zenoh wiring (``app``), the
fixed-rate loop (``loop``), the car it steps (``slot``), the load worker, the pacer
(``realtime``) and its log files (``logfile``)."""
