"""Small numpy rigid-transform helpers for the reference world.

Conventions: quaternions are (w, x, y, z) unless a name says ``xyzw`` (the ROS
order); rotation matrices are [3, 3]; homogeneous transforms are [4, 4] and
map child coordinates to parent coordinates (``p_parent = T @ p_child``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = [
    "quat_to_mat",
    "mat_to_quat",
    "rpy_to_mat",
    "make_T",
    "invert_T",
    "look_at_optical",
    "MJ_FROM_OPTICAL",
    "rotation_angle_deg",
    "so3_log",
]

#: Rotation taking an optical frame (x right, y down, z forward) to MuJoCo's
#: camera frame (x right, y up, z backward): R_mj = R_optical @ MJ_FROM_OPTICAL.
MJ_FROM_OPTICAL = np.diag([1.0, -1.0, -1.0])


def quat_to_mat(q: Sequence[float]) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> rotation matrix [3, 3]."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def mat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] -> unit quaternion (w, x, y, z) with w >= 0."""
    m = np.asarray(R, dtype=float)
    t = np.trace(m)
    cands = [t, m[0, 0] - m[1, 1] - m[2, 2], m[1, 1] - m[0, 0] - m[2, 2], m[2, 2] - m[0, 0] - m[1, 1]]
    i = int(np.argmax(cands))
    s = 2.0 * np.sqrt(max(1.0 + cands[i], 1e-12))
    if i == 0:
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif i == 1:
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif i == 2:
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def rpy_to_mat(rpy: Sequence[float]) -> np.ndarray:
    """URDF roll-pitch-yaw (fixed axes x, then y, then z; radians) -> [3, 3]."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def make_T(R: np.ndarray, t: Sequence[float]) -> np.ndarray:
    """Rotation [3, 3] and translation [3] -> homogeneous transform [4, 4]."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float)
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform [4, 4]."""
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def look_at_optical(eye: Sequence[float], target: Sequence[float], up: Sequence[float]) -> np.ndarray:
    """Rotation [3, 3] of an optical frame at ``eye`` looking at ``target``.

    Columns are the optical axes in the parent frame: z forward (towards the
    target), x right, y down; ``up`` is the parent-frame direction that should
    appear upwards in the image (it must not be parallel to the view ray).
    """
    z = np.asarray(target, dtype=float) - np.asarray(eye, dtype=float)
    if np.linalg.norm(z) < 1e-9:
        raise ValueError("camera look_at target coincides with the camera position")
    z /= np.linalg.norm(z)
    down = -np.asarray(up, dtype=float)
    x = np.cross(down, z)
    if np.linalg.norm(x) < 1e-6:
        raise ValueError(f"camera 'up' {list(up)} is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, radians) [3] of a rotation matrix [3, 3]."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-9:
        return 0.5 * v
    if np.pi - angle < 1e-6:
        # Near pi: axis from the symmetric part.
        A = (R + np.eye(3)) / 2.0
        axis = A[:, int(np.argmax(np.diag(A)))]
        axis = axis / np.linalg.norm(axis)
        return axis * angle
    return v * (angle / (2.0 * np.sin(angle)))


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle in degrees of the relative rotation between two rotation matrices."""
    return float(np.degrees(np.linalg.norm(so3_log(Ra.T @ Rb))))
