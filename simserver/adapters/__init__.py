"""Adapters between the compiled core and the outside world (files, plots, network)."""
