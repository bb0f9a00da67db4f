"""Analytic kinematics of the Bioscara's tool centre point (TCP).

The TCP is the site ``tcp`` of ``assets/bioscara.xml``: midway between the
fingertips, on the j4 axis, so its position depends on j1, j2 and j3 only.
Link lengths are the URDF's (docs/model.md); the height at j2 = 0 is the model's
vertical geometry (fingertips 5 mm above the table top). Used on every
backend, so a policy sees the same ``achieved_goal`` on the real arm.
"""

from __future__ import annotations

import math

import numpy as np

#: j1 axis to j3 axis, m (URDF).
L1 = 0.329476
#: j3 axis to j4 axis, m (URDF).
L2 = 0.285
#: TCP height above the table at j2 = 0, m (``assets/bioscara.xml``).
TCP_Z0 = 0.005


def forward(q: np.ndarray) -> np.ndarray:
    """TCP position (x, y, z) in m for joint positions ``q = (j1, j2, j3, j4, ...)``.

    Accepts a batch: ``q`` of shape ``(..., >=3)`` gives ``(..., 3)``.
    """
    q = np.asarray(q, dtype=float)
    q1, q2, q3 = q[..., 0], q[..., 1], q[..., 2]
    a = q1 + q3
    return np.stack(
        (L1 * np.cos(q1) + L2 * np.cos(a), L1 * np.sin(q1) + L2 * np.sin(a), TCP_Z0 + q2), axis=-1
    )


def inverse(xyz: np.ndarray, elbow: float = 1.0) -> tuple[float, float, float] | None:
    """Joint positions (j1, j2, j3) that put the TCP at ``xyz``.

    Args:
        xyz: Target (x, y, z) in m.
        elbow: Sign of j3 in the solution (+1 or -1).

    Returns:
        ``(j1, j2, j3)``, or ``None`` when the point is out of planar reach.
    """
    x, y, z = (float(v) for v in xyz)
    r2 = x * x + y * y
    c3 = (r2 - L1 * L1 - L2 * L2) / (2 * L1 * L2)
    if not -1.0 <= c3 <= 1.0:
        return None
    q3 = math.copysign(math.acos(c3), elbow)
    q1 = math.atan2(y, x) - math.atan2(L2 * math.sin(q3), L1 + L2 * math.cos(q3))
    q1 = (q1 + math.pi) % (2 * math.pi) - math.pi
    return q1, z - TCP_Z0, q3
