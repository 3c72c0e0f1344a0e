"""Where a path that ``get_config`` shows lives on this machine.

The server shows its file paths (vehicle, scene) relative to its config folders, never
absolute (``docs/security.md``); a client
or the viewer on the same installation finds the file under the same folders. Light on
purpose (``pathlib`` only): the driver clients import it without the compiled core."""

from __future__ import annotations

from pathlib import Path

CONFIG_FOLDERS = (Path(__file__).resolve().parents[2] / "configs",)
"""The folders a shown path is looked up in: this installation's ``configs/``."""


def local_config_file(shown: str) -> Path:
    """The local file of a path as ``get_config`` shows it: absolute paths as they are,
    relative ones under the first config folder that has them, else under the working
    directory."""
    path = Path(shown)
    if path.is_absolute():
        return path
    for folder in CONFIG_FOLDERS:
        if (folder / path).is_file():
            return folder / path
    return Path.cwd() / path
