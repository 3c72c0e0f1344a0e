"""Digest of the published VehicleState bytes, to compare two trees bit for bit.

The real vehicle slot (``VehicleSlot.fill_state``, the bytes the loop publishes) on the
real simulation, 3000 ticks on the flat, the 10 % hill and the hills height map, driven,
steered and braked, with catch-up ticks and a moving command clock; one SHA-256 per scene.
Run it with ``PYTHONPATH`` at each tree and compare the lines::

    PYTHONPATH=/path/to/before python -m benchmarks.state_wire_digest
    PYTHONPATH=/path/to/after  python -m benchmarks.state_wire_digest

(issue 29 item 5: the state table changed how the state is filled, not its bytes.)
"""

from __future__ import annotations

import hashlib
import math

SCENES = ("flat_paper_sedan", "hill_10pct_paper_sedan", "hills_paper_sedan")
TICKS = 3000


def digests(ticks: int = TICKS) -> dict[str, str]:
    """Scene name -> SHA-256 of the concatenated state payloads of ``ticks`` ticks."""
    from simserver.core import layout as L
    from simserver.server.app import new_simulation
    from simserver.server.config import DEFAULT_SERVER_CONFIG, REPO_CONFIGS, load_server_config
    from simserver.server.slot import VehicleSlot
    from simserver.sim.scene import load_scene

    cfg = load_server_config(DEFAULT_SERVER_CONFIG, viewer="off")
    out = {}
    for name in SCENES:
        scene = load_scene(REPO_CONFIGS / "scenes" / f"{name}.yaml")
        slot = VehicleSlot(cfg, new_simulation(scene, cfg.period_s))
        h = hashlib.sha256()
        for k in range(ticks):
            inputs = slot.sim.inputs
            inputs[L.IN_GEAR] = L.GEAR_D
            inputs[L.IN_THROTTLE] = 0.6 if k < 2 * ticks // 3 else 0.0
            inputs[L.IN_BRAKE] = 0.0 if k < 2 * ticks // 3 else 0.8
            inputs[L.IN_STEER] = 0.3 * math.sin(k * 0.003)
            slot.advance()
            h.update(slot.fill_state(1_000_000 * k, k % 7 == 0))
        out[name] = h.hexdigest()
    return out


if __name__ == "__main__":
    for scene, digest in digests().items():
        print(scene, digest)
