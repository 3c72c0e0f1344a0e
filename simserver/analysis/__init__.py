"""Figures read from a run's history (the columns of ``history.parquet``): what a
vehicle-dynamics engineer looks for first (``holds``: every stop held, its creep, its
restart's rollback; ``compare``: two histories aligned, resampled and differenced, for
the ``compare`` subcommand, ``cli``). No physics core, no I/O but the subcommand's: arrays
in, plain numbers out, so a headless run, a soak, a sweep and a live recording are judged
alike."""
