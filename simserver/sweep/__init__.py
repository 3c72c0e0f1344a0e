"""Sweeps, the ``sweep`` subcommand: many scenario runs on Dask distributed (issue 18).

- ``resolved``: a run's fully resolved configuration, dotted-path overrides, its hash.
- ``spec``: the sweep file (base scenarios, parameters, metrics) -> cases.
- ``metrics``: numbers extracted from one run.
- ``worker``: running a batch of cases (what a Dask task does).
- ``engine``: the Dask client, batching, the results table, resume.
- ``report``: plots and the Markdown report.
"""
