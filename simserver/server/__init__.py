"""The live 1 kHz server: its settings (``config``, one reader per key), its command log
read back and replayed bit for bit (``command_log``), its zenoh wiring (``app``), the
fixed-rate loop with controls dispatched through a table (``loop``), the car it steps
with its arbitration and watchdog (``slot``; both tested in-process,
``tests/test_server_logic.py``), scene loads off the tick (``load_worker``), the pacer
(``realtime``) and its log files opened without following links and written off the tick
(``logfile``); several cars in one world (issue 30): the ``cars:`` list and its checks
(``cars_config``), the cars' world and the world message (``fleet``), cars added and
removed while it runs (``world_desk``), cars driven by the built-in driver
(``live_drivers``), a session of several cars replayed in one world from every car's
command log (``world_replay``); an OpenSCENARIO scenario served live, its storyboard on a
worker thread (``scenario_live``, issue 31)."""
