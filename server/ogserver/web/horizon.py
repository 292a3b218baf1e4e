"""Which way is up in a map's world, for a viewer that keeps the horizon level: estimated from the keyframes'
camera axes, since datasets differ (OpenCV-style ones have +y down, the synthetic room z up).

People pitch a camera freely but seldom roll it, so the cameras' right axes lie close to the horizontal
plane while their up axes lean with the pitch (a camera looking down at a table leans its up axis
forward). Up is therefore the direction most nearly perpendicular to every right axis; where the right
axes span too little to fix it (one camera, or a path that never turns), the cameras' mean up fills in.
"""

from __future__ import annotations

import numpy as np

# How much the cameras' mean up weighs against the right axes: small, so only directions the right axes leave
# undetermined take it (in the units of the right axes' mean outer product, whose trace is 1).
MEAN_UP_WEIGHT = 1e-4


def world_up(c2w: np.ndarray) -> list[float] | None:
    """The world's up as a unit vector from camera-to-world poses (n, 4, 4) in OpenCV axes (x right, y down,
    z forward); None without poses."""
    if len(c2w) == 0:
        return None
    rights = c2w[:, :3, 0]
    mean_up = -c2w[:, :3, 1].mean(axis=0)
    up = np.linalg.solve(rights.T @ rights / len(rights) + MEAN_UP_WEIGHT * np.eye(3), mean_up)
    return (up / np.linalg.norm(up)).tolist()
