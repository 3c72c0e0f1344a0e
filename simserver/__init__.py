"""simserver: a real-time driving-simulator server built on the lagged-slip tire
formulation of SAE 950311 (Bernard & Clover, 1995).

Layers (imports point one way, toward the core):

- ``simserver.core``: pure numba-compiled physics (state layout, parameters, tires,
  chassis, powertrain, integrator). No I/O.
- ``simserver.adapters``: configuration (YAML, .tir), output files, plots.
- ``simserver.cli``: the command line.
"""

__version__ = "0.1.0"
