"""Zenoh clients of the simserver protocol: a driver, a maneuver player and a recorder.

They use only the published contract: :mod:`simserver.wire.protocol` (the codec of
``docs/protocol.md``) and :mod:`simserver.adapters.zenoh_io` (sessions with safe
defaults). They never import the server, its physics core or its configuration loaders,
so they prove that the contract is enough to drive a car (the player also reads the
scenario *file format* through :mod:`simserver.sim.keyframes`, the headless runner's keyframe
parser and sampler, which loads neither numba nor the compiled core).

Modules
-------
common
    Connection flags, the start-up check ("is a server there?"), exit codes, a rate pacer
    on absolute deadlines and signal handling shared by the three programs.
driver
    ``simserver-driver``: drive the car from a terminal keyboard (works over SSH)
    or a game controller / steering wheel through pygame (SDL2), with a live status.
keyboard
    Raw terminal input (termios), key decoding and the keyboard driving model (held keys
    from key repeat, pedal ramps, auto-centring rate-limited steering).
joystick
    Joystick profiles (YAML, validated), the pure axis/button mapping, the pygame device
    wrapper and SDL's virtual joystick (a scripted device for demos and tests).
player
    ``simserver-player``: play a scenario's input keyframes live, in real time.
recorder
    ``simserver-recorder``: record state and diagnostics to Parquet with the
    headless runner's column names.
"""
