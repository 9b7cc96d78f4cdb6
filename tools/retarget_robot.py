#!/usr/bin/env python3
"""Rewrite bags recorded with one robot as if another robot had done the same manipulation.

    python tools/retarget_robot.py SRC_DATASET OUT --to arx5 [--from panda]
        [--base X Y Z YAW_DEG] [--max-error-mm 1.0]

The object, the cameras and every image stay as recorded; what changes is the robot: its
``/joint_states`` become the target robot's joints, solved by inverse kinematics so that its
jaws follow the recorded jaws (same tip position, same approach and closing axes, same opening
in metres); ``/tf_static`` gets the target's base link (``--base``, default: where the source's
base was) and its wrist camera mount (the camera keeps its pose relative to the jaws);
``/robot_description`` becomes the target's URDF; the source's link tree on ``/tf`` and its joint
efforts are dropped. Masks recorded in the bags are kept (the images still show the source
robot, so masks derived from the target's URDF would not match them), and so is the reference
world's evaluation-only ``/world/object_points`` (Chamfer stays comparable).

A trainer fed the retargeted bags with ``robot=<target>`` sees the same control-point motion as
the original with ``robot=<source>``, to the difference of the two jaws' shapes: a check that a
robot other than the reference world's trains and runs end to end. A frame whose pose the target
cannot reach within ``--max-error-mm`` (and 0.5 degrees) is refused, naming the bag and the frame.

Robots are named as for ``soma train --set robot=...`` (``config/robots/<name>.yaml`` or a path).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "tools"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from rig_bags import RigForm, rewrite_bag  # noqa: E402

from soma_ros.viewer.tf_graph import transform_to_matrix  # noqa: E402

ROT_TOL_DEG = 0.5


def jaw_frame(robot) -> np.ndarray:
    """T_ee_jaw [4, 4]: origin at the jaws' tip centre, x the approach axis, y the closing axis."""
    cp = robot.config.control_points
    a = np.asarray(cp.approach_axis, float)
    a /= np.linalg.norm(a)
    c = np.asarray(cp.closing_axis, float)
    c = c - a * (c @ a)
    c /= np.linalg.norm(c)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = a, c, np.cross(a, c)
    T[:3, 3] = a * float(cp.tip_offset)
    return T


def _set_pose(tr, T: np.ndarray) -> None:
    """Write [4, 4] into a geometry_msgs/Transform."""
    from soma_ros.core.geometry import rotmat_to_quat

    w, x, y, z = (float(v) for v in rotmat_to_quat(torch.as_tensor(T[:3, :3], dtype=torch.float64)))
    tr.rotation.w, tr.rotation.x, tr.rotation.y, tr.rotation.z = w, x, y, z
    tr.translation.x, tr.translation.y, tr.translation.z = (float(v) for v in T[:3, 3])


def _rot_err_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


class ArmSolver:
    """Damped least squares on the robot's own FK and Jacobian, warm-started frame to frame."""

    def __init__(self, robot, seeds: int = 24, seed: int = 0) -> None:
        self.robot = robot
        self.n_arm = len(robot.arm_joint_names)
        lo, hi = robot.joint_limits()
        self.lo, self.hi = lo.numpy()[: self.n_arm], hi.numpy()[: self.n_arm]
        self.q: Optional[np.ndarray] = None
        self.seeds = seeds
        self.gen = torch.Generator().manual_seed(seed)

    def _q_full(self, qa: np.ndarray):
        q = np.zeros((qa.shape[0], self.robot.n_joints))
        q[:, : self.n_arm] = qa
        return torch.as_tensor(q, dtype=torch.float64)

    def _solve_from(self, qa: np.ndarray, target: np.ndarray, iters: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """qa [B, n_arm] -> (q, position error m [B], rotation error deg [B])."""
        lam = 1e-3
        for _ in range(iters):
            T = self.robot.ee_pose(self._q_full(qa)).numpy()
            dp = target[None, :3, 3] - T[:, :3, 3]
            Re = target[None, :3, :3] @ np.transpose(T[:, :3, :3], (0, 2, 1))
            dw = 0.5 * np.stack([Re[:, 2, 1] - Re[:, 1, 2], Re[:, 0, 2] - Re[:, 2, 0], Re[:, 1, 0] - Re[:, 0, 1]], 1)
            e = np.concatenate([dp, 0.3 * dw], 1)  # [B, 6]; rotation weighted (m per rad)
            if np.abs(e).max() < 1e-10:
                break
            J = self.robot.ee_jacobian(self._q_full(qa)).numpy()[:, :, : self.n_arm]
            J[:, 3:] *= 0.3
            JT = np.transpose(J, (0, 2, 1))
            dq = JT @ np.linalg.solve(J @ JT + lam * np.eye(6)[None], e[..., None])
            qa = np.clip(qa + dq[..., 0], self.lo, self.hi)
        T = self.robot.ee_pose(self._q_full(qa)).numpy()
        perr = np.linalg.norm(T[:, :3, 3] - target[None, :3, 3], axis=1)
        rerr = np.array([_rot_err_deg(T[b, :3, :3], target[:3, :3]) for b in range(qa.shape[0])])
        return qa, perr, rerr

    def solve(self, target: np.ndarray) -> tuple[np.ndarray, float, float]:
        """target T_base_ee [4, 4] -> (arm joints [n_arm], position error m, rotation error deg)."""
        if self.q is not None:
            qa, pe, re = self._solve_from(self.q[None], target, 60)
            if pe[0] < 1e-4 and re[0] < 0.05:
                self.q = qa[0]
                return qa[0], float(pe[0]), float(re[0])
        lo = np.where(np.isfinite(self.lo), self.lo, -math.pi)
        hi = np.where(np.isfinite(self.hi), self.hi, math.pi)
        u = torch.rand(self.seeds, self.n_arm, generator=self.gen, dtype=torch.float64).numpy()
        starts = lo + u * (hi - lo)
        if self.q is not None:
            starts = np.concatenate([self.q[None], starts])
        qa, pe, re = self._solve_from(starts, target, 200)
        b = int(np.argmin(pe + 1e-3 * re))
        self.q = qa[b]
        return qa[b], float(pe[b]), float(re[b])


FLIP = np.diag([1.0, -1.0, -1.0, 1.0])  # a half turn about the approach axis: the same two jaws


@dataclass
class Retarget:
    """The ``alter`` of :func:`rig_bags.rewrite_bag` for one bag: source robot -> target robot.

    :meth:`plan` reads the bag first: the source's base from ``/tf_static`` and its jaw pose at
    every ``/joint_states`` message, and solves the target's joints for all of them, once with
    the target's jaw frame as configured and once turned half a turn about the approach axis
    (two parallel jaws look the same either way); the form that reaches every pose best is
    kept for the whole bag, so a wrist camera's mount stays one fixed transform.
    """

    source: object  # RobotModel
    target: object  # RobotModel
    base: Optional[np.ndarray] = None  # T_world_targetbase [4, 4]; None: the source's base
    max_error_m: float = 1e-3
    bag: str = ""

    def plan(self, bag: Path) -> dict:
        from rosbags.highlevel import AnyReader

        from soma_ros.bagtypes import typestore

        J_src = jaw_frame(self.source)
        T_wb, jaws, openings = None, [], []
        with AnyReader([Path(bag)], default_typestore=typestore()) as r:
            for c, _, raw in r.messages([x for x in r.connections if x.topic in ("/tf_static", "/joint_states")]):
                msg = r.deserialize(raw, c.msgtype)
                if c.topic == "/tf_static":
                    for tr in msg.transforms:
                        if tr.child_frame_id == self.source.base_link:
                            T_wb = transform_to_matrix(tr.transform)
                    continue
                names, pos = list(msg.name), np.asarray(msg.position, float)[None]
                q = self.source.q_from_joint_state(names, pos).to(torch.float64)
                jaws.append(self.source.ee_pose(q).numpy()[0] @ J_src)
                openings.append(float(self.source.gripper_state(names, pos)[0][0]))
        if T_wb is None:
            raise ValueError(f"{self.bag}: /tf_static does not place the source robot's base '{self.source.base_link}'")
        if not jaws:
            raise ValueError(f"{self.bag}: no /joint_states")
        if self.base is None:
            self.base = T_wb.copy()
        best = None
        for flip in (np.eye(4), FLIP):
            J_tgt = jaw_frame(self.target) @ flip
            solver, qs, worst = ArmSolver(self.target), [], (0.0, 0.0)
            for k, T_sb_jaw in enumerate(jaws):
                T_tb_ee = np.linalg.inv(self.base) @ T_wb @ T_sb_jaw @ np.linalg.inv(J_tgt)
                qa, pe, re = solver.solve(T_tb_ee)
                qs.append(qa)
                worst = (max(worst[0], pe), max(worst[1], re))
                if pe > self.max_error_m or re > ROT_TOL_DEG:
                    worst = (max(worst[0], pe), max(worst[1], re), k)
                    break
            if best is None or worst[0] + 1e-3 * worst[1] < best[2][0] + 1e-3 * best[2][1]:
                best = (J_tgt, qs, worst)
        self.J_src, (self.J_tgt, self.q, worst) = J_src, best
        if len(worst) == 3:
            raise ValueError(f"{self.bag}: frame {worst[2]}: robot '{self.target.config.name}' cannot reach the "
                             f"recorded jaw pose (error {worst[0] * 1e3:.2f} mm, {worst[1]:.2f} deg); move its base (--base)")
        self.openings, self.frames = openings, 0
        # the target's opening model is linear in its gripper values: every gripper joint gets one value
        n = len(self.target.gripper_joint_names)
        self.open_offset = float(self.target.opening_from_values(torch.zeros(n, dtype=torch.float64)))
        self.open_slope = float(self.target.opening_from_values(torch.ones(n, dtype=torch.float64))) - self.open_offset
        return {"frames": len(jaws), "worst_mm": worst[0] * 1e3, "worst_deg": worst[1]}

    def _joint_state(self, msg):
        qa, open_m = self.q[self.frames], self.openings[self.frames]
        self.frames += 1
        tj = self.target.gripper_joint_names
        lo, hi = self.target.opening_range
        gv = [(min(max(open_m, float(lo)), float(hi)) - self.open_offset) / self.open_slope] * len(tj)
        msg.name = list(self.target.arm_joint_names) + list(tj)
        msg.position = np.concatenate([qa, np.asarray(gv, float)])
        msg.velocity = np.zeros(0)
        msg.effort = np.zeros(0)
        return msg

    def _tf_static(self, msg):
        for tr in msg.transforms:
            if tr.child_frame_id == self.source.base_link:
                tr.child_frame_id = self.target.base_link
                _set_pose(tr.transform, self.base)
            elif tr.header.frame_id in self.source.link_names:
                # a mount on a source link (a wrist camera): rebuilt on the target's ee link, at the
                # same pose relative to the jaws
                if tr.header.frame_id != self.source.ee_link:
                    raise ValueError(f"{self.bag}: /tf_static mounts '{tr.child_frame_id}' on source link "
                                     f"'{tr.header.frame_id}', not on its ee link '{self.source.ee_link}'")
                T_jaw_cam = np.linalg.inv(self.J_src) @ transform_to_matrix(tr.transform)
                tr.header.frame_id = self.target.ee_link
                _set_pose(tr.transform, self.J_tgt @ T_jaw_cam)
        return msg

    def __call__(self, topic: str, msg):
        if topic == "/joint_states":
            return self._joint_state(msg)
        if topic == "/tf_static":
            return self._tf_static(msg)
        if topic == "/robot_description":
            msg.data = Path(self.target.config.urdf).read_text()
        return msg


def base_pose(xyz_yaw: Sequence[float]) -> np.ndarray:
    x, y, z, yaw = (float(v) for v in xyz_yaw)
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [x, y, z]
    return T


def retarget_bag(src: Path, dst: Path, source, target, base: Optional[np.ndarray] = None,
                 max_error_m: float = 1e-3) -> dict:
    """Rewrite one bag (module docstring); returns {frames, worst_mm, worst_deg}."""
    alter = Retarget(source, target, base=None if base is None else np.asarray(base, float),
                     max_error_m=max_error_m, bag=Path(src).name)
    info = alter.plan(Path(src))
    rewrite_bag(Path(src), Path(dst), RigForm(keep_ground_truth=True), drop=("/tf",), alter=alter)
    assert alter.frames == info["frames"], (alter.frames, info)
    return info


def main(argv=None) -> int:
    import json
    import shutil

    from soma_ros.core.robot import RobotModel
    from soma_ros.data.sources import find_bags

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[2], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--from", dest="source", default="panda", help="the robot the bags were recorded with")
    ap.add_argument("--to", dest="target", required=True, help="the robot to retarget to")
    ap.add_argument("--base", type=float, nargs=4, metavar=("X", "Y", "Z", "YAW_DEG"),
                    help="the target's base in the world frame (default: the source's base)")
    ap.add_argument("--max-error-mm", type=float, default=1.0)
    a = ap.parse_args(argv)
    source = RobotModel.from_config(a.source, dtype=torch.float64)
    target = RobotModel.from_config(a.target, dtype=torch.float64)
    a.out.mkdir(parents=True, exist_ok=True)
    try:
        bags = find_bags(a.src)
    except Exception as e:  # noqa: BLE001 - one line for the user
        print(f"retarget_robot: {e}", file=sys.stderr)
        return 2
    for bag in bags:
        dst = a.out / bag.name
        if dst.exists():
            shutil.rmtree(dst)
        try:
            info = retarget_bag(bag, dst, source, target, None if a.base is None else base_pose(a.base),
                                a.max_error_mm * 1e-3)
        except ValueError as e:
            print(f"retarget_robot: {e}", file=sys.stderr)
            return 1
        print(f"{bag.name}: {info['frames']} frames, worst jaw pose error {info['worst_mm']:.3f} mm, "
              f"{info['worst_deg']:.3f} deg")
    for side in [a.src / "manifest.json", *(a.src / f"{b.name}.meta.json" for b in bags)]:
        if side.is_file():  # the split, and the reference world's evaluation-only sidecars
            shutil.copy(side, a.out / side.name)
    print(json.dumps({"out": str(a.out), "bags": len(bags)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
