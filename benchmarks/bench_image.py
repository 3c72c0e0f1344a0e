"""The container image's start: ``simserver serve`` from the image's environment to its
``ready`` line, every kernel loaded from the cache the image's build pre-compiled.

    python -m benchmarks.bench_image              # build the environment, 3 starts
    python -m benchmarks.bench_image --starts 5 --keep /tmp/image   # keep it for next time
    python -m benchmarks.bench_image --reuse /tmp/image             # time a kept one again

No container engine is needed: the environment is built as ``tests/test_dockerfile.py``'s
long form builds it (the Dockerfile's own COPY, ENV, WORKDIR and RUN instructions carried out
below a scratch root: the builder's ``pip install .`` into a fresh venv, then the image's
warm-up, which compiles every kernel into its ``SIMSERVER_CACHE_DIR`` and checks a fresh
process finds them all). Then the image's ``ENTRYPOINT`` + ``CMD`` is started ``--starts``
times (listening on a free loopback port instead of ``0.0.0.0:7447``), each to its ``ready``
line and stopped: the median wall time and the server's CPU seconds at ready. A start that
compiles anything (says "compiling", or writes to the cache) is an error, not a figure.
Issue 33's target: under 2 s. Building takes minutes (``pip install`` of every dependency
from the local wheels, a cold compile of every kernel).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
TARGET_S = 2.0
"""Issue 33: the server starts in under 2 s from the image's environment."""


def build(where: Path) -> dict[str, Any]:
    """Build the image's environment below ``where`` (``tests/test_dockerfile.py``'s
    emulation); ``{"build_s", "env", "cwd"}``."""
    from tests.test_dockerfile import DOCKERFILE, image_context, parse_dockerfile, run_dockerfile

    stages = parse_dockerfile(DOCKERFILE.read_text(encoding="utf-8"))[1]
    t0 = time.monotonic()
    root, context, base_bin = image_context(where)
    emu = run_dockerfile(stages, root, context, base_bin)
    shutil.rmtree(context, ignore_errors=True)
    info = {"build_s": time.monotonic() - t0, "env": emu.env, "cwd": str(emu.cwd)}
    (where / "image.json").write_text(json.dumps(info, indent=1), encoding="utf-8")
    return info


def time_starts(where: Path, starts: int) -> dict[str, Any]:
    """``starts`` starts of the image's ENTRYPOINT + CMD from the environment built below
    ``where``: wall seconds to ready and the server's CPU seconds then, per start."""
    from benchmarks.__main__ import _cpu_s
    from tests.test_dockerfile import (
        DOCKERFILE,
        Emulation,
        ImageRoot,
        cache_listing,
        parse_dockerfile,
        start_image_server,
    )

    final = parse_dockerfile(DOCKERFILE.read_text(encoding="utf-8"))[1][-1]
    info = json.loads((where / "image.json").read_text(encoding="utf-8"))
    emu = Emulation(env=info["env"], cwd=Path(info["cwd"]), log=[])
    cache = Path(emu.env["SIMSERVER_CACHE_DIR"])
    before = cache_listing(cache)
    if not before:
        raise SystemExit(f"{cache}: the image's kernel cache is empty (not built?)")
    wall: list[float] = []
    cpu: list[float] = []
    for _ in range(starts):
        server = start_image_server(final, ImageRoot(where / "root"), emu, ready_timeout_s=300)
        cpu.append(_cpu_s(server.pid))
        server.stop()
        text = server.text()
        if "compiling" in text or cache_listing(cache) != before:
            raise RuntimeError("the image's server compiled at its start (the pre-compiled "
                               f"cache was not used):\n{text}")
        wall.append(server.ready_s)
        print(f"image start: ready in {wall[-1]:.2f} s ({cpu[-1]:.2f} s CPU; load average "
              f"{os.getloadavg()[0]:.1f})", flush=True)
    return {"ready_s": wall, "cpu_s": cpu, "ready_median_s": statistics.median(wall),
            "cpu_median_s": statistics.median(cpu), "kernel_files": len(before)}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Build (or reuse) the image's environment, time its starts, print and return them."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_image",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--starts", type=int, default=3, help="starts to time (median)")
    parser.add_argument("--keep", type=Path, default=None, metavar="DIR",
                        help="build the environment in DIR and keep it")
    parser.add_argument("--reuse", type=Path, default=None, metavar="DIR",
                        help="time the environment a --keep run left in DIR (no build)")
    args = parser.parse_args(argv)
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    where = args.reuse or args.keep or Path(tempfile.mkdtemp(prefix="simserver_image_"))
    try:
        result: dict[str, Any] = {"build_s": None}
        if args.reuse is None:
            print(f"building the image's environment in {where} (minutes)", flush=True)
            result["build_s"] = build(where)["build_s"]
            print(f"built in {result['build_s']:.0f} s", flush=True)
        result.update(time_starts(where, args.starts))
    finally:
        if args.keep is None and args.reuse is None:
            shutil.rmtree(where, ignore_errors=True)
    print(f"image start to ready: median {result['ready_median_s']:.2f} s of "
          f"{len(result['ready_s'])} ({result['cpu_median_s']:.2f} s CPU); target < "
          f"{TARGET_S:g} s", flush=True)
    return result


if __name__ == "__main__":
    main()
