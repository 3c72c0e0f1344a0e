"""The pure compiled core: no I/O, no zenoh, no rerun, no YAML.

Everything here works on flat float64 arrays with named index constants and is
compiled with ``numba.njit(cache=True)``.
"""
