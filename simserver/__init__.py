"""simserver: a real-time driving-simulator server built on the lagged-slip tire
formulation of SAE 950311 (Bernard & Clover, 1995). The top level holds the command line
(``cli``, its subcommands ``serve``, ``replay``, ``run-scenario``, ``soak``, ``view``,
``ros2``, ``sweep``, ``compare``, ``tire-curves``), the errors several rooms raise (``errors``) and
the package run as a program (``__main__``).

The rooms, the core first, in the order imports mostly point (``README.md``'s table is
generated from their docstrings by ``docs/rooms.py``; ``tests/test_import_cycles.py`` fails
on any import cycle between modules):

- ``core``: pure numba-compiled physics (state layout, parameters, tires, chassis,
  powertrain, the world and its step). No I/O.
- ``tires``: the tire-model registry and each model's loader beside its registration.
- ``wire``: the wire contract and the published state's one table.
- ``adapters``: configuration files, histories, plots, zenoh, Rerun, the viewer.
- ``sim``: a scene made into a car of a world; scenarios, keyframes, the soak.
- ``analysis``: figures from a history; the ``compare`` subcommand.
- ``server``: the live 1 kHz server.
- ``ros2``, ``sweep``: the ROS 2 adapter; sweeps on Dask.
- ``testing``: the harness tests and benchmarks start servers with.

The edges that go up a room, each from a module no lower module imports back: the tire
loaders read with ``adapters.validate`` and ``adapters.tir_file`` (below
``adapters.config``, which reads the tires); the adapters that write a run's files take
its result type and figures (``sim.scenario``, ``analysis``); ``adapters.zenoh_io`` and
``adapters.rerun_sink`` take file helpers from ``server.realtime`` and ``server.logfile``;
the server starts the ROS 2 adapter (``ros2.cli``), which logs through ``server.logfile``.
"""

__version__ = "0.1.0"
