"""Errors that several rooms raise, in a module that imports nothing of the package, so
the rooms that raise them (``simserver.ros2.cli``, ``simserver.analysis.cli``) need not
import the command line that reports them (``simserver.cli``).

``ConfigError`` (a bad file or value, named with its key) lives with the value checks,
``simserver.adapters.validate``, which is as low.
"""

from __future__ import annotations


class CliError(Exception):
    """An error to report as ``error: <message>`` with the given exit code."""

    def __init__(self, message: str, exit_code: int = 1) -> None:
        super().__init__(message)
        self.exit_code = exit_code
