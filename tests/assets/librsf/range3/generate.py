"""Write the synthetic 3-D ranging excerpt of this folder (``R3x_Input.txt``, ``R3x_GT.txt``).

A simulated vehicle climbing and descending while it turns (40 s at 5 Hz), six fixed anchors at
heights 0-14 m, libRSF records: ``odom3`` (body velocity forward/left/up and yaw rate, noise
0.05 m/s and 0.01 rad/s), ``range3`` (noise 0.1 m, the file's variance 0.01 m^2; 10 % of the
ranges carry a positive non-line-of-sight error of 0.5-3 m; anchor 2 reads 0.4 m long) and
``point3`` truth.  The motion is integrated the way the odometry convention of
:mod:`difffilter.datasets.ranging` reads it (each record moves the vehicle from the previous time
with the previous heading).  Run from the repository root: ``python tests/assets/librsf/range3/generate.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

ANCHORS = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 14.0], [30.0, 30.0, 1.0], [0.0, 30.0, 12.0], [15.0, -5.0, 8.0], [-5.0, 15.0, 2.0]])
BIAS = np.array([0.0, 0.0, 0.4, 0.0, 0.0, 0.0])


def main(folder: Path | None = None, steps: int = 200, dt: float = 0.2, seed: int = 0) -> None:
    folder = Path(__file__).resolve().parent if folder is None else folder
    rng = np.random.default_rng(seed)
    t = np.arange(steps) * dt
    speed = 1.5 + 0.7 * np.sin(0.3 * t)
    yaw_rate = 0.25 * np.cos(0.15 * t)
    climb = 0.3 * np.cos(0.25 * t)
    pos, yaw = np.zeros((steps, 3)), np.zeros(steps)
    pos[0], yaw[0] = [5.0, 5.0, 5.0], 0.3
    for k in range(1, steps):
        c, s = np.cos(yaw[k - 1]), np.sin(yaw[k - 1])
        pos[k] = pos[k - 1] + dt * np.array([c * speed[k], s * speed[k], climb[k]])
        yaw[k] = yaw[k - 1] + dt * yaw_rate[k]
    lines = []
    for k in range(1, steps):
        v = [speed[k] + 0.05 * rng.standard_normal(), 0.05 * rng.standard_normal(), climb[k] + 0.05 * rng.standard_normal()]
        w = yaw_rate[k] + 0.01 * rng.standard_normal()
        var = [0.0025, 0.0025, 0.0025, 1e-4, 1e-4, 1e-4]
        lines.append(f"odom3 {t[k]:.1f} {v[0]:.6f} {v[1]:.6f} {v[2]:.6f} 0 0 {w:.6f} " + " ".join(f"{x:g}" for x in var))
    for k in range(steps):
        d = np.linalg.norm(pos[k] - ANCHORS, axis=1) + BIAS + 0.1 * rng.standard_normal(len(ANCHORS))
        nlos = rng.random(len(ANCHORS)) < 0.1
        d = d + nlos * rng.uniform(0.5, 3.0, len(ANCHORS))
        for a, (r, anc) in enumerate(zip(d, ANCHORS, strict=True)):
            lines.append(f"range3 {t[k]:.1f} {r:.6f} 0.01 {anc[0]:g} {anc[1]:g} {anc[2]:g} {a + 1} 0")
    lines.sort(key=lambda ln: float(ln.split()[1]))  # time order; odometry first within a time stamp (stable sort)
    (folder / "R3x_Input.txt").write_text("\n".join(lines) + "\n")
    gt = [f"point3 {t[k]:.1f} {pos[k, 0]:.6f} {pos[k, 1]:.6f} {pos[k, 2]:.6f}" for k in range(steps)]
    (folder / "R3x_GT.txt").write_text("\n".join(gt) + "\n")


if __name__ == "__main__":
    main()
