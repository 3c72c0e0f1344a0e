"""One simulation: a scene (``scene``: a vehicle on a terrain at a start, parsed from its
files top to bottom) made into a car of a world and stepped by the compiled core
(``simulation``: ``World``, the cars of one terrain, added or removed between steps with
nothing recompiled, and ``Simulation``, one car of it, used by every runner: server,
replay, scenarios, soak, sweep worker, benchmarks); headless scenarios of one car or of
several on one terrain (``scenario``) with their keyframed inputs (``keyframes``, parsed
and sampled without the core, also for the player; or driven closed loop by the built-in
driver, ``core.driver``, or held at a speed for the constant-speed manoeuvres,
``speed_hold``), OpenSCENARIO files played with physical cars (``xosc_run``,
docs/openscenario.md), any scene file by its kind, YAML or ``.xosc`` (``scene_files``),
the seeded soak (``soak``) and its multi-car form (``multisoak``: a bumping pair, traffic
on the built-in driver, random drives, in one world)."""
