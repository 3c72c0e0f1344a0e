"""The hostile ``ctl/load`` files of issue 13, shared by the live-path test and
``benchmarks.bench_load --hostile``: a valid 10 MB scene, a YAML alias bomb, a deeply
nested file and a FIFO named as a scene."""
from __future__ import annotations

import os
from pathlib import Path

from simserver.testing import CONFIGS


def hostile_files(tmp: Path) -> dict[str, Path]:
    """The hostile ``load`` files of issue 13 in ``tmp``: a 10 MB scene (valid YAML), an
    alias bomb, a deeply nested file, a FIFO."""
    vehicle = CONFIGS / "vehicles" / "paper_sedan" / "vehicle.yaml"
    big = tmp / "big_scene.yaml"
    filler = "# " + "x" * 98 + "\n"
    big.write_text(f"name: big\nvehicle: {vehicle}\n"
                   "road: {grade_pct: 2.0, cross_slope_pct: 0.0, friction_scale: 1.0}\n"
                   "initial: {x_m: 0.0, y_m: 0.0, yaw_rad: 0.0, u_mps: 0.0}\n"
                   + filler * (10 * 1024 * 1024 // len(filler)), encoding="utf-8")
    bomb = tmp / "bomb.yaml"
    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i, name in enumerate("bcdefg"):
        lines.append(f"{name}: &{name} [" + ",".join([f"*{'abcdefg'[i]}"] * 9) + "]")
    bomb.write_text("\n".join(lines) + f"\nvehicle: {vehicle}\n", encoding="utf-8")
    deep = tmp / "deep.yaml"
    deep.write_text("vehicle: " + "[" * 50_000 + "]" * 50_000 + "\n", encoding="utf-8")
    fifo = tmp / "fifo.yaml"
    os.mkfifo(fifo)
    return {"big": big, "bomb": bomb, "deep": deep, "fifo": fifo}
