"""Validation of configuration values and safe reading of configuration files.

The helpers every loader uses (vehicle and tire files, scenes, scenarios, the keyframe
reader of :mod:`simserver.sim.keyframes`, the server config, .tir files). They import only the
standard library and PyYAML, so a client can validate a scenario's keyframes without
loading numba or :mod:`simserver.core`. Every error is a :class:`ConfigError` whose
message names the file and the key.

Reading a file (:func:`read_config_bytes`, :func:`read_yaml`) is bounded, because a
server reads files named by its clients (the ``load`` control): regular files only (no
FIFO, device or directory: a FIFO would block the reader forever), at most
:data:`MAX_CONFIG_BYTES`, YAML nested at most :data:`MAX_YAML_DEPTH` deep and expanding
through its aliases to at most :data:`MAX_YAML_NODES` nodes (a "billion laughs" file is
refused before anything walks it). Inside :func:`confined_to` every file read, and every
file a config refers to (:func:`referenced_file`), must lie in the given folders; the
server's ``load`` control reads under it (``docs/security.md``).
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import os
import stat
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import yaml

__all__ = ["MAX_CONFIG_BYTES", "MAX_YAML_DEPTH", "MAX_YAML_NODES", "ConfigError",
           "check_keys", "choice", "confined_to", "display_path", "integer", "is_path_text",
           "number", "parse_yaml", "read_config_bytes", "read_yaml", "referenced_file",
           "report_progress", "set_progress_sink", "short_repr"]

MAX_CONFIG_BYTES = 4 << 20
"""Largest configuration file read (4 MiB; the shipped ones are below 20 KiB)."""
MAX_YAML_DEPTH = 64
"""Deepest nesting of YAML collections accepted (the shipped configs nest 3 deep)."""
MAX_YAML_NODES = 200_000
"""Most YAML nodes a document may expand to, every alias counted as a copy."""
MAX_YAML_INT_CHARS = 1000
"""Longest integer scalar (Python refuses to convert more than 4 300 digits; no setting
needs more than 20)."""


class ConfigError(ValueError):
    """A configuration file is missing, unreadable or invalid; the message names file and key."""


_progress_sink: Any = None


def set_progress_sink(sink: Any) -> None:
    """Where :func:`report_progress` goes: a callable taking the message (the server's load
    worker: ``simserver.server.load_worker``), or None (nowhere: the default)."""
    global _progress_sink
    _progress_sink = sink


def report_progress(message: str) -> None:
    """A long read saying how far it got (``FILE: 3 of 80 MiB read``); the server's load
    worker counts these as signs of life and logs the last one (``simserver.server.load_worker``).
    Cheap when nobody listens."""
    if _progress_sink is not None:
        _progress_sink(message)


_CONFINED: contextvars.ContextVar[tuple[Path, ...] | None] = contextvars.ContextVar(
    "simserver_config_roots", default=None)


@contextlib.contextmanager
def confined_to(roots: Sequence[Path]) -> Iterator[None]:
    """Within the block, read configuration files only inside ``roots`` (resolved)."""
    token = _CONFINED.set(tuple(Path(r).resolve() for r in roots))
    try:
        yield
    finally:
        _CONFINED.reset(token)


def display_path(path: Path | str, roots: Sequence[Path] | None = None) -> str:
    """``path`` relative to the first of ``roots`` (default: the confinement) holding it.

    What a reply to a client may show: never the server's absolute folders. A path in
    none of them is shown by its file name only.
    """
    path = Path(path)
    for root in roots if roots is not None else (_CONFINED.get() or ()):
        root = Path(root)
        if path.is_relative_to(root):
            return path.relative_to(root).as_posix()
    return path.name if path.is_absolute() else path.as_posix()


def _check_confined(path: Path, label: str) -> None:
    roots = _CONFINED.get()
    if roots is not None and not any(path.is_relative_to(r) for r in roots):
        raise ConfigError(f"{label} outside the server's config directories")


def is_path_text(value: Any) -> bool:
    """A non-empty string the file system can take: no NUL, no lone surrogate."""
    if not isinstance(value, str) or not value or "\0" in value:
        return False
    try:
        os.fsencode(value)
    except UnicodeError:
        return False
    return True


def referenced_file(referrer: Path | str, key: str, value: Any) -> Path:
    """The file that key ``key`` of config file ``referrer`` refers to, resolved.

    ``value`` must be a non-empty path string, relative to the referrer's folder (or
    absolute); the file must exist, be a regular file and, inside :func:`confined_to`,
    lie in the confined folders. Errors name the referring file and the key.
    """
    referrer = Path(referrer)
    if not is_path_text(value):
        raise ConfigError(f"{referrer}: key '{key}': expected a file path, got "
                          f"{short_repr(value)}")
    target = (referrer.parent / value).resolve()
    _check_confined(target, f"{referrer}: key '{key}': refers to a file")
    try:
        mode = os.stat(target).st_mode
    except OSError as exc:
        raise ConfigError(f"{referrer}: key '{key}': {target}: "
                          f"{exc.strerror or 'cannot read'}") from None
    if not stat.S_ISREG(mode):
        raise ConfigError(f"{referrer}: key '{key}': {target}: not a regular file")
    return target


def read_regular_chunks(path: Path, limit: int, chunk_bytes: int,
                        error: type[ConfigError] = ConfigError,
                        what: str = "the most such a file may have") -> Iterator[bytes]:
    """The bytes of the regular file ``path`` in chunks, at most ``limit`` in all.

    Opened non-blocking and checked with ``fstat`` after opening, so a FIFO or device
    swapped in is refused without blocking (or hanging the reader); a file larger than
    ``limit`` at ``fstat``, or grown past it while read, is refused. Errors are ``error``
    naming ``path`` ("cannot read: larger than 256 bytes ({what})")."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except (OSError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise error(f"{path}: cannot read: {reason}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise error(f"{path}: cannot read: not a regular file")
        if info.st_size > limit:
            raise error(f"{path}: cannot read: larger than {limit} bytes ({what}): "
                        f"{info.st_size} bytes")
        done = 0
        with os.fdopen(os.dup(fd), "rb") as f:
            while chunk := f.read(chunk_bytes):
                done += len(chunk)
                if done > limit:  # grown since fstat
                    raise error(f"{path}: cannot read: larger than {limit} bytes ({what})")
                yield chunk
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def read_config_bytes(path: Path | str, limit: int = MAX_CONFIG_BYTES) -> bytes:
    """The bytes of a configuration file: regular, at most ``limit`` (default
    :data:`MAX_CONFIG_BYTES`), read by :func:`read_regular_chunks`; inside
    :func:`confined_to`, the resolved file must lie in the confined folders.
    """
    path = Path(path)
    if not is_path_text(str(path)):
        raise ConfigError(f"{short_repr(str(path))}: cannot read: not a valid file name")
    _check_confined(path.resolve(), f"{path}: a file")
    return b"".join(read_regular_chunks(path, limit, limit + 1,
                                        what="the most a configuration file may have"))


class _BoundedLoader(yaml.SafeLoader):
    """PyYAML's safe loader with a depth limit while composing (the composer recurses)."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        self._depth += 1
        if self._depth > MAX_YAML_DEPTH:
            mark = self.peek_event().start_mark
            raise yaml.YAMLError(f"nested deeper than {MAX_YAML_DEPTH} levels "
                                 f"(line {mark.line + 1})")
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        if len(node.value) > MAX_YAML_INT_CHARS:
            raise yaml.constructor.ConstructorError(
                None, None, f"an integer of {len(node.value)} characters (at most "
                f"{MAX_YAML_INT_CHARS})", node.start_mark)
        return super().construct_yaml_int(node)

    def construct_object(self, node: yaml.Node, deep: bool = False) -> Any:
        try:
            return super().construct_object(node, deep)
        except (ValueError, OverflowError) as exc:  # a scalar its type refuses: 2001-13-45
            raise yaml.constructor.ConstructorError(
                None, None, f"a {node.tag.rsplit(':', 1)[-1]} its type cannot take "
                f"({type(exc).__name__})", node.start_mark) from None


_BoundedLoader.add_constructor("tag:yaml.org,2002:int", _BoundedLoader.construct_yaml_int)


def _expanded_nodes(root: yaml.Node) -> int:
    """Nodes of ``root`` with every alias expanded (shared nodes counted per use)."""
    sizes: dict[int, int] = {}
    visiting: set[int] = set()

    def size(node: yaml.Node) -> int:
        known = sizes.get(id(node))
        if known is not None:
            return known
        if id(node) in visiting:  # a: &a [*a]: no configuration is infinite
            raise yaml.YAMLError("an alias refers to a node that contains it")
        visiting.add(id(node))
        total = 1
        if isinstance(node, yaml.SequenceNode):
            total += sum(size(child) for child in node.value)
        elif isinstance(node, yaml.MappingNode):
            total += sum(size(k) + size(v) for k, v in node.value)
        visiting.discard(id(node))
        sizes[id(node)] = total
        return total

    return size(root)


def parse_yaml(path: Path | str, text: str) -> Any:
    """The YAML document in ``text`` within the limits above; errors name the file and
    the line but never quote the text (it may be a file the client must not see)."""
    try:
        loader = _BoundedLoader(text)  # its reader refuses control characters at once
    except yaml.reader.ReaderError as exc:
        raise ConfigError(f"{path}: not valid YAML: character #x{exc.character:04x} is not "
                          f"allowed (position {exc.position})") from None
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        if _expanded_nodes(node) > MAX_YAML_NODES:
            raise ConfigError(f"{path}: not valid YAML: expands to more than "
                              f"{MAX_YAML_NODES} nodes through its aliases")
        return loader.construct_document(node)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        raise ConfigError(f"{path}: not valid YAML: {exc.problem or exc.context}{where}") \
            from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    except ConfigError:
        raise
    except (ValueError, OverflowError) as exc:  # a scalar its type refuses: 2001-13-45
        raise ConfigError(f"{path}: not valid YAML: a value its type cannot take "
                          f"({type(exc).__name__})") from None
    except RecursionError:  # aliases chained or recursive (a: &a [*a]) past the stack
        raise ConfigError(f"{path}: not valid YAML: aliases nested too deeply or "
                          "recursively") from None
    finally:
        loader.dispose()


def read_yaml(path: Path | str) -> dict[str, Any]:
    """Read a YAML mapping, with errors naming the file."""
    raw = read_config_bytes(path)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    data = parse_yaml(path, text)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys to values at the top level")
    return data


def short_repr(value: Any, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters, for error messages (a client's or a
    fuzzer's value may be megabytes long)."""
    try:
        text = repr(value)
    except ValueError:  # an int too long for repr (sys.set_int_max_str_digits)
        return f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[:limit - 3] + "..."


def number(path: Path | str, key: str, value: Any, lo: float, hi: float) -> float:
    """Validate one finite, normal number within ``[lo, hi]``; errors name file and key.

    Subnormal numbers (non-zero, below 2.2e-308 in magnitude) are refused too: dividing
    by one overflows to infinity, whatever the range (``FNOMIN = 1e-320``).
    """
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{path}: key '{key}': expected a number, got {short_repr(value)}")
    try:
        val = float(value)
    except OverflowError:
        raise ConfigError(f"{path}: key '{key}': the number is too large") from None
    if not math.isfinite(val):
        raise ConfigError(f"{path}: key '{key}': must be finite, got {short_repr(value)}")
    if val != 0.0 and abs(val) < sys.float_info.min:
        raise ConfigError(f"{path}: key '{key}': {val:g} is subnormal (use 0 or a normal "
                          "number)")
    if not lo <= val <= hi:
        raise ConfigError(f"{path}: key '{key}': {val:g} is outside [{lo:g}, {hi:g}]")
    return val


def integer(path: Path | str, key: str, value: Any, lo: int, hi: int) -> int:
    """Validate one integer within ``[lo, hi]`` (``1.5`` is refused, not truncated)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{path}: key '{key}': expected an integer, got {short_repr(value)}")
    if not lo <= value <= hi:
        raise ConfigError(f"{path}: key '{key}': {short_repr(value)} is outside [{lo}, {hi}]")
    return value


def choice(path: Path | str, key: str, value: Any, names: dict[str, int]) -> int:
    """Validate a named choice; errors list the accepted names."""
    if not isinstance(value, str) or value not in names:
        raise ConfigError(
            f"{path}: key '{key}': expected one of {sorted(names)}, got {short_repr(value)}"
        )
    return names[value]


def check_keys(path: Path | str, data: dict[str, Any], allowed: tuple[str, ...] | set[str],
               required: tuple[str, ...] | set[str] = ()) -> None:
    """Reject unknown keys and report missing ones, naming the file."""
    for key in data:
        if key not in allowed:
            raise ConfigError(
                f"{path}: unknown key {short_repr(key)} (allowed: {', '.join(sorted(allowed))})"
            )
    for key in required:
        if key not in data:
            raise ConfigError(f"{path}: missing key '{key}'")
