"""Figures read from a run's history (the columns of ``history.parquet``): what a
vehicle-dynamics engineer looks for first (``holds``: every stop held, its creep, its
restart's rollback; ``compare``: two histories aligned, resampled and differenced, for
the ``compare`` subcommand, ``cli``; ``manoeuvres``: the standard manoeuvres' figures and
pass criteria with the clause each comes from, ISO 4138, ISO 7401, FMVSS 126, hill starts,
FMVSS 105, ISO 3888-2, docs/manoeuvres.md). No physics core, no I/O but the subcommand's: arrays
in, plain numbers out, so a headless run, a soak, a sweep and a live recording are judged
alike."""
