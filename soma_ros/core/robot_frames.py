"""A robot's link transforms from joint states, as robot_state_publisher computes them.

:class:`RobotFrames` turns a URDF and a joint state (names, positions) into one
``(parent_link, child_link, T_parent_child [4, 4])`` per URDF joint:

* fixed joints: the joint origin, once (they go on ``/tf_static``);
* revolute / continuous joints: ``origin @ Rot(axis, value)``;
* prismatic joints: ``origin @ Trans(axis * value)``.

``<mimic>`` joints take ``multiplier * leader + offset``; a movable joint that
the joint state does not name is held at 0 clamped into its limits (as the FK
of :class:`~soma_ros.core.robot.RobotModel` holds it). ``floating`` and
``planar`` joints have no single joint value and stay at their origin.

:func:`robot_description` gives the URDF text to publish on
``/robot_description``, with every mesh reference made an absolute ``file://``
URI so RViz and other viewers find the meshes outside the package tree.

Pure numpy, no ROS: the live node, the reference world's bag recorder and the
browser viewer use the same transforms.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Sequence, Union

import numpy as np

from .robot_urdf import UrdfJoint, UrdfModel, parse_urdf, resolve_mesh_path

__all__ = ["RobotFrames", "robot_description", "rpy_matrix"]


def rpy_matrix(xyz: Sequence[float], rpy: Sequence[float]) -> np.ndarray:
    """URDF <origin>: [4, 4] with translation xyz and R = Rz(yaw) Ry(pitch) Rx(roll), float64."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    T = np.eye(4)
    T[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                 [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                 [-sp, cp * sr, cp * cr]]
    T[:3, 3] = [float(v) for v in xyz]
    return T


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: unit axis [3], angles [B] -> rotations [B, 3, 3]."""
    k = axis / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    R = np.eye(3)[None] + s * K[None] + (1.0 - c) * (K @ K)[None]
    assert R.shape == (angle.shape[0], 3, 3)
    return R


class RobotFrames:
    """The transforms of every URDF joint, from joint states (see the module docstring)."""

    def __init__(self, urdf: Union[UrdfModel, str, Path]) -> None:
        self.urdf: UrdfModel = urdf if isinstance(urdf, UrdfModel) else parse_urdf(urdf)
        self.root: str = self.urdf.root
        self._origin = {j.name: rpy_matrix(j.origin_xyz, j.origin_rpy) for j in self.urdf.joints.values()}
        self.fixed_joints: list[UrdfJoint] = [j for j in self.urdf.joints.values() if j.type == "fixed"]
        #: joints whose transform depends on a joint value (plus floating / planar ones, held at their origin)
        self.moving_joints: list[UrdfJoint] = [j for j in self.urdf.joints.values() if j.type != "fixed"]

    @property
    def links(self) -> list[str]:
        return list(self.urdf.links)

    def static_transforms(self) -> list[tuple[str, str, np.ndarray]]:
        """(parent, child, T [4, 4]) of every fixed joint: robot_state_publisher's /tf_static."""
        return [(j.parent, j.child, self._origin[j.name].copy()) for j in self.fixed_joints]

    def joint_values(self, names: Sequence[str], positions: np.ndarray) -> dict[str, np.ndarray]:
        """{movable joint: values [B]} from a joint state (names [J], positions [J] or [B, J])."""
        pos = np.asarray(positions, dtype=np.float64)
        if pos.ndim == 1:
            pos = pos[None]
        if pos.ndim != 2 or pos.shape[1] != len(names):
            raise ValueError(f"joint state has {len(names)} names but positions of shape {np.shape(positions)}")
        given = {n: pos[:, i] for i, n in enumerate(names)}
        out: dict[str, np.ndarray] = {}
        for j in self.urdf.joints.values():
            if j.type not in ("revolute", "continuous", "prismatic"):
                continue
            leader, mult, off = self.urdf.mimic_root(j.name)
            if leader in given:
                v = mult * given[leader] + off
            else:
                lj = self.urdf.joints[leader]
                held = min(max(0.0, -math.inf if lj.lower is None else lj.lower), math.inf if lj.upper is None else lj.upper)
                v = np.full(pos.shape[0], mult * held + off)
            out[j.name] = v
        return out

    def moving_transforms(self, names: Sequence[str], positions: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
        """(parent, child, T [B, 4, 4]) of every non-fixed joint for a joint state
        (positions [J] gives B = 1): robot_state_publisher's /tf."""
        values = self.joint_values(names, positions)
        B = next(iter(values.values())).shape[0] if values else np.atleast_2d(np.asarray(positions)).shape[0]
        out = []
        for j in self.moving_joints:
            T = np.repeat(self._origin[j.name][None], B, axis=0)
            if j.name in values:
                v = values[j.name]
                axis = np.asarray(j.axis, dtype=np.float64)
                M = np.repeat(np.eye(4)[None], B, axis=0)
                if j.type == "prismatic":
                    M[:, :3, 3] = v[:, None] * axis[None] / np.linalg.norm(axis)
                else:
                    M[:, :3, :3] = _axis_angle(axis, v)
                T = T @ M
            assert T.shape == (B, 4, 4)
            out.append((j.parent, j.child, T))
        return out

    def link_poses(self, names: Sequence[str], positions: np.ndarray) -> dict[str, np.ndarray]:
        """{link: T_root_link [B, 4, 4]} for a joint state: the transforms chained from the root."""
        tf = {c: (p, T) for p, c, T in self.moving_transforms(names, positions)}
        B = next(iter(tf.values()))[1].shape[0] if tf else 1
        for p, c, T in self.static_transforms():
            tf[c] = (p, np.repeat(T[None], B, axis=0))
        poses: dict[str, np.ndarray] = {self.root: np.repeat(np.eye(4)[None], B, axis=0)}

        def pose(link: str) -> np.ndarray:
            if link not in poses:
                parent, T = tf[link]
                poses[link] = pose(parent) @ T
            return poses[link]

        for link in self.urdf.links:
            pose(link)
        return poses


_MESH_RE = re.compile(r'(<mesh\b[^>]*\bfilename\s*=\s*)(["\'])(.*?)\2')


def robot_description(urdf_path: Union[str, Path]) -> str:
    """The URDF's text for /robot_description, mesh references made absolute ``file://`` URIs
    (a mesh that cannot be found keeps its reference unchanged)."""
    path = Path(urdf_path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise FileNotFoundError(f"cannot read URDF {path}: {exc.strerror or exc}") from None

    def absolute(m: re.Match) -> str:
        try:
            uri = resolve_mesh_path(m.group(3), path.parent).as_uri()
        except FileNotFoundError:
            uri = m.group(3)
        return f"{m.group(1)}{m.group(2)}{uri}{m.group(2)}"

    return _MESH_RE.sub(absolute, text)
