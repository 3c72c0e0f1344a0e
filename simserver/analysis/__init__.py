"""Figures read from a run's history (the columns of ``history.parquet``): what a
vehicle-dynamics engineer looks for first. No physics core, no I/O: arrays in, plain
numbers out, so a headless run, a soak, a sweep and a live recording are judged alike."""
