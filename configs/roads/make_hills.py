"""Generate ``hills.npz``: the height map of the terrain tests and scenes.

Along world x (the car drives along +x, y = 0 is the middle of the map):

- a hill of 6 m at x = 40 m, a dip of 2 m at x = 90 m between it and a hill of 8 m at
  x = 140 m (Gaussian profiles: grades up to about 21 %);
- flat ground from x = 170 m on, with a sharp bump under the left wheels only at
  x = 200 m: 0.10 m high, 0.8 m long (raised cosine), from y = 0.1 m to y = 2 m with
  0.4 m raised-cosine flanks (smooth, so the C1 interpolation holds);
- a patch of low friction (scale 0.3) at 215 m <= x <= 225 m.

Run ``python configs/roads/make_hills.py`` (numpy only); the result is deterministic.
"""

from pathlib import Path

import numpy as np

CELL_M = 0.25
X0_M, X1_M = -10.0, 230.0
Y0_M, Y1_M = -6.0, 6.0
BUMP_X_M, BUMP_LENGTH_M, BUMP_HEIGHT_M = 200.0, 0.8, 0.10


def raised_cosine(t: np.ndarray) -> np.ndarray:
    """1 at t = 0 falling smoothly to 0 at |t| = 1 (and 0 beyond)."""
    return np.where(np.abs(t) < 1.0, 0.5 * (1.0 + np.cos(np.pi * np.clip(t, -1.0, 1.0))), 0.0)


def ramp(y: np.ndarray, lo: float, hi: float, flank: float) -> np.ndarray:
    """1 on [lo, hi], raised-cosine flanks of width ``flank`` outside, 0 beyond."""
    below = raised_cosine((y - lo) / flank) * (y < lo)
    above = raised_cosine((y - hi) / flank) * (y > hi)
    return np.where((y >= lo) & (y <= hi), 1.0, below + above)


def heights_and_friction() -> tuple[np.ndarray, np.ndarray]:
    x = np.arange(X0_M, X1_M + 0.5 * CELL_M, CELL_M)
    y = np.arange(Y0_M, Y1_M + 0.5 * CELL_M, CELL_M)
    xx, yy = np.meshgrid(x, y)  # [row j = y, column i = x]
    hills = (6.0 * np.exp(-(((xx - 40.0) / 25.0) ** 2))
             + 8.0 * np.exp(-(((xx - 140.0) / 25.0) ** 2))
             - 2.0 * np.exp(-(((xx - 90.0) / 15.0) ** 2)))
    hills = np.where(xx < 170.0, hills, hills * raised_cosine((xx - 170.0) / 5.0))
    bump = BUMP_HEIGHT_M * raised_cosine((xx - BUMP_X_M) / (0.5 * BUMP_LENGTH_M)) * ramp(
        yy, 0.1, 2.0, 0.4)
    friction = np.where((xx >= 215.0) & (xx <= 225.0), 0.3, 1.0)
    return (hills + bump).astype(np.float32), friction.astype(np.float32)


if __name__ == "__main__":
    heights, friction = heights_and_friction()
    out = Path(__file__).with_name("hills.npz")
    np.savez_compressed(out, heights=heights, friction=friction)
    print(f"{out}: {heights.shape[1]} x {heights.shape[0]} samples, {CELL_M} m cells, "
          f"origin ({X0_M}, {Y0_M}) m")
