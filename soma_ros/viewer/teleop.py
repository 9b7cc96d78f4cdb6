"""End-effector teleop of a robot through its own IK: a jog in the simulation frame -> joints.

:class:`EndEffectorJog` keeps a target for the robot's tool centre (the mean of its
control points, between the jaws) and a target orientation (approach axis along
gravity, the jaws closing along a horizontal axis), and solves the arm joints for
it on the robot's differentiable FK (:class:`~soma_ros.core.robot.RobotModel`),
warm-started from the current joints, so any URDF the simulator supports can be
jogged. A jog the arm cannot follow (out of reach, a joint limit) leaves the
joints and the target where they were and says so.

Coordinates are the simulation frame; the robot base -> simulation similarity of the
scene bundle converts them.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np
import torch

__all__ = ["EndEffectorJog", "JogRefused"]


class JogRefused(ValueError):
    """A jog the arm cannot follow; the joints are unchanged."""


class EndEffectorJog:
    def __init__(self, robot, base_to_sim: np.ndarray, names: Sequence[str], gravity: Sequence[float],
                 tolerance_m: float = 2e-3) -> None:
        """``robot``: RobotModel; ``base_to_sim`` [4, 4] similarity; ``names``: the joint vector's
        names (a LiveSimulator's ``required_joints``)."""
        self.robot = robot.to(dtype=torch.float64)
        self.names = list(names)
        M = np.asarray(base_to_sim, dtype=np.float64)
        assert M.shape == (4, 4), M.shape
        self.scale = float(np.cbrt(abs(np.linalg.det(M[:3, :3]))))
        self.R = M[:3, :3] / self.scale
        self.t = M[:3, 3]
        g = np.asarray(gravity, dtype=np.float64)
        self.down_base = self.R.T @ (g / np.linalg.norm(g))
        self.tolerance = float(tolerance_m)
        grip = set(self.robot.gripper_joint_names)
        self.arm_idx = [i for i, n in enumerate(self.robot.joint_names) if n not in grip]
        self.grip_idx = [i for i, n in enumerate(self.robot.joint_names) if n in grip]
        lo, hi = self.robot.joint_limits()
        self.lo, self.hi = lo.numpy(), hi.numpy()
        mid = np.where(np.isfinite(self.lo) & np.isfinite(self.hi), 0.5 * (self.lo + self.hi), 0.0)
        self.q = mid.copy()
        self.gripper_open = True
        self._set_gripper(True)
        self.target: Optional[np.ndarray] = None

    # ------------------------------------------------------------------ frames
    def to_base(self, p_sim: np.ndarray) -> np.ndarray:
        return self.R.T @ ((np.asarray(p_sim, dtype=np.float64) - self.t) / self.scale)

    def to_sim(self, p_base: np.ndarray) -> np.ndarray:
        return self.scale * (self.R @ np.asarray(p_base, dtype=np.float64)) + self.t

    def _set_gripper(self, open_: bool) -> None:
        """Every gripper joint of q at the end of its range that opens (or closes) the jaws,
        by the robot's own opening model."""
        self.gripper_open = bool(open_)
        names = self.robot.gripper_joint_names
        for i in self.grip_idx:
            lo, hi = self.lo[i], self.hi[i]
            if not (np.isfinite(lo) and np.isfinite(hi)):
                self.q[i] = 0.0
                continue
            k = names.index(self.robot.joint_names[i])
            v = torch.zeros(2, len(names), dtype=torch.float64)
            v[0, k], v[1, k] = lo, hi
            o_lo, o_hi = (float(x) for x in self.robot.opening_from_values(v))
            opens_high = o_hi >= o_lo
            self.q[i] = (hi if opens_high else lo) if open_ else (lo if opens_high else hi)

    def _opening(self, q: torch.Tensor) -> torch.Tensor:
        if not self.robot.gripper_joint_names:
            return torch.zeros(1, dtype=torch.float64)
        lo, hi = self.robot.opening_range
        return torch.tensor([hi if self.gripper_open else lo], dtype=torch.float64)

    def tcp(self, q: Optional[np.ndarray] = None) -> np.ndarray:
        """The tool centre [3] in the simulation frame for FK vector q (default: the current one)."""
        qt = torch.tensor(self.q if q is None else q, dtype=torch.float64)[None]
        cp = self.robot.control_points(qt, self._opening(qt))[0]
        return self.to_sim(cp.mean(0).numpy())

    # ------------------------------------------------------------------ IK
    def _target_rotation(self, closing_sim: Sequence[float]) -> torch.Tensor:
        z = self.down_base
        y = self.R.T @ np.asarray(closing_sim, dtype=np.float64)
        y = y - z * (y @ z)
        if np.linalg.norm(y) < 1e-6:
            y = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
        y /= np.linalg.norm(y)
        # ee frame: its approach axis along gravity, its closing axis along y
        cfg = self.robot.config.control_points
        a = np.asarray(cfg.approach_axis, dtype=np.float64)
        c = np.asarray(cfg.closing_axis, dtype=np.float64)
        a, c = a / np.linalg.norm(a), c / np.linalg.norm(c)
        E = np.stack([a, c, np.cross(a, c)], axis=1)  # ee axes in the ee frame
        W = np.stack([z, y, np.cross(z, y)], axis=1)  # where they should point, base frame
        return torch.tensor(W @ E.T, dtype=torch.float64)

    def solve(self, tcp_sim: Sequence[float], closing_sim: Sequence[float] = (0.0, 1.0, 0.0),
              q0: Optional[np.ndarray] = None, iters: int = 80) -> tuple[np.ndarray, float]:
        """(FK vector q, position error m) with the tool centre at `tcp_sim`."""
        target = torch.tensor(self.to_base(tcp_sim), dtype=torch.float64)
        R_t = self._target_rotation(closing_sim)
        q_full = torch.tensor(self.q if q0 is None else q0, dtype=torch.float64)
        lo = torch.tensor(np.where(np.isfinite(self.lo), self.lo, -math.pi))
        hi = torch.tensor(np.where(np.isfinite(self.hi), self.hi, math.pi))
        arm = q_full[self.arm_idx].clone().requires_grad_(True)
        opening = self._opening(q_full)

        def full(a: torch.Tensor) -> torch.Tensor:
            q = q_full.clone()
            q[self.arm_idx] = torch.minimum(torch.maximum(a, lo[self.arm_idx]), hi[self.arm_idx])
            return q[None]

        opt = torch.optim.LBFGS([arm], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            q = full(arm)
            p = self.robot.control_points(q, opening)[0].mean(0)
            R = self.robot.ee_pose(q)[0, :3, :3]
            loss = 100.0 * ((p - target) ** 2).sum() + 0.1 * ((R - R_t) ** 2).sum()
            loss.backward()
            return loss

        with torch.enable_grad():
            opt.step(closure)
        with torch.no_grad():
            q = full(arm.detach())
            err = float((self.robot.control_points(q, opening)[0].mean(0) - target).norm()) * self.scale
        return q[0].numpy(), err

    def home(self, tcp_sim: Sequence[float], seeds: int = 6) -> float:
        """Put the tool centre at `tcp_sim` from the mid-range pose (and random restarts); returns the error."""
        gen = torch.Generator().manual_seed(0)
        best = None
        for k in range(seeds):
            q0 = self.q.copy()
            if k:
                q0[self.arm_idx] = self.robot.sample_q(1, generator=gen)[0].double().numpy()[self.arm_idx]
            q, err = self.solve(tcp_sim, q0=q0)
            if best is None or err < best[1]:
                best = (q, err)
            if err < self.tolerance:
                break
        self.q = best[0]
        self._set_gripper(self.gripper_open)
        self.target = np.asarray(tcp_sim, dtype=np.float64)
        return best[1]

    def jog(self, delta_sim: Sequence[float]) -> np.ndarray:
        """Move the tool-centre target by `delta_sim` [3] m; returns the new joint vector."""
        return self.move_to((self.target if self.target is not None else self.tcp()) + np.asarray(delta_sim, float))

    def move_to(self, tcp_sim: Sequence[float]) -> np.ndarray:
        q, err = self.solve(tcp_sim)
        if err > self.tolerance:
            raise JogRefused(f"the arm cannot reach {np.round(np.asarray(tcp_sim, float), 3).tolist()} "
                             f"(misses by {err * 1e3:.0f} mm)")
        self.q = q
        self._set_gripper(self.gripper_open)
        self.target = np.asarray(tcp_sim, dtype=np.float64)
        return self.joint_vector()

    def set_gripper(self, open_: bool) -> np.ndarray:
        self._set_gripper(open_)
        return self.joint_vector()

    def joint_vector(self) -> np.ndarray:
        """The joint vector in ``names`` order (gripper joints of the URDF from q; external ones from
        the opening)."""
        index = {n: i for i, n in enumerate(self.robot.joint_names)}
        out = np.zeros(len(self.names), dtype=np.float64)
        ext = dict(self.robot.config.gripper.external_joints) if self.robot.config.gripper else {}
        for k, n in enumerate(self.names):
            if n in index:
                out[k] = self.q[index[n]]
            elif n in ext:
                lo, hi = ext[n]
                out[k] = hi if self.gripper_open else lo
        return out
