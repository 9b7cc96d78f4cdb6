"""Robot conditioning: batched FK, joint-state mapping, gripper state, control points.

This is the robot half of the paper's R2S mapping (Sec. 3, "Robot
Conditioning"): joint states q_t -> end-effector pose T^ee_rob(t) = FK(q_t) in
the robot base frame, the gripper state c_t in [0, 1], and the 30 robot
control points r_j^t that the interaction graph connects to the splats. The
robot -> simulation similarity transform lives in :mod:`soma_ros.core.calibration`.

Conventions
-----------
* Poses are 4x4 homogeneous matrices ``T_base_link`` mapping link-frame
  coordinates to base-frame coordinates, float32 by default.
* The FK joint vector ``q`` [B, n_joints] holds :attr:`RobotModel.joint_names`:
  the arm joints in config order, then the gripper joints that exist in the
  URDF. URDF ``<mimic>`` joints are never part of q; they are filled in as
  ``multiplier * leader + offset`` (pytorch_kinematics ignores <mimic>).
  Movable URDF joints that are neither in q nor mimic joints (other branches)
  are held at 0 clamped into their limits.
* Gripper opening: metres between the jaws; c = 0 closed, c = 1 fully open.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np
import torch

from soma_ros.core.robot_config import (
    ControlPointConfig,
    GripperConfig,
    OpeningModel,
    RobotConfig,
    RobotConfigError,
    load_robot_config,
)
from soma_ros.core.robot_urdf import URDFError, UrdfJoint, UrdfModel, parse_urdf

__all__ = [
    "RobotModel",
    "RobotConfig",
    "GripperConfig",
    "OpeningModel",
    "ControlPointConfig",
    "RobotConfigError",
    "URDFError",
    "load_robot_config",
    "control_point_pattern",
]

ArrayLike = Union[torch.Tensor, np.ndarray, Sequence[float], Sequence[Sequence[float]]]


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def control_point_pattern(cfg: ControlPointConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The opening-independent part of the control points, in float64.

    Returns ``(base [P, 3], side [P], closing_axis [3])`` such that the control
    points in the ee frame at opening o are ``base + side[:, None] * (o / 2) * closing_axis``.
    Jaw +1 (side = +1) comes first, then jaw -1; within a jaw, points run
    tip-first along the approach axis, then across the width.
    """
    a = torch.tensor(cfg.approach_axis, dtype=torch.float64)
    c = torch.tensor(cfg.closing_axis, dtype=torch.float64)
    a = a / a.norm()
    c = c / c.norm()
    w = torch.linalg.cross(a, c)
    rows, cols = cfg.grid
    u = torch.linspace(0.0, 1.0, rows, dtype=torch.float64) if rows > 1 else torch.zeros(1, dtype=torch.float64)
    v = torch.linspace(-0.5, 0.5, cols, dtype=torch.float64) if cols > 1 else torch.zeros(1, dtype=torch.float64)
    uu, vv = torch.meshgrid(u, v, indexing="ij")
    jaw = (cfg.tip_offset - uu.reshape(-1, 1) * cfg.jaw_length) * a + vv.reshape(-1, 1) * cfg.jaw_width * w  # [R*C, 3]
    base = torch.cat([jaw, jaw], dim=0)
    side = torch.cat([torch.ones(rows * cols, dtype=torch.float64), -torch.ones(rows * cols, dtype=torch.float64)])
    assert base.shape == (cfg.count, 3) and side.shape == (cfg.count,)
    return base, side, c


class RobotModel:
    """A URDF robot for conditioning the simulator, with batched torch FK.

    Build with ``RobotModel(RobotConfig.from_yaml(...))`` or
    ``RobotModel.from_config("panda")``. Raises :class:`URDFError` /
    :class:`RobotConfigError` (both ValueError) with a one-line message naming
    the unusable element.
    """

    def __init__(
        self,
        config: RobotConfig,
        *,
        dtype: torch.dtype = torch.float32,
        device: Union[str, torch.device] = "cpu",
    ) -> None:
        import pytorch_kinematics as pk  # heavy import, kept local

        self.config = config
        self.dtype = dtype
        self.device = torch.device(device)
        urdf = parse_urdf(config.urdf)
        self.urdf: UrdfModel = urdf
        src = urdf.source
        self.base_link: str = config.base_link or urdf.root
        urdf.require_link(self.base_link, "base_link")
        urdf.require_link(config.ee_link, "ee_link")
        self.ee_link: str = config.ee_link
        #: joints on the path base_link -> ee_link (fixed ones included), base first
        self.chain_joints: list[UrdfJoint] = urdf.path_joints(self.base_link, self.ee_link)

        # ---- gripper joints: in the URDF (part of q) or external (joint state only)
        gcfg = config.gripper or GripperConfig()
        for j in gcfg.joints:
            if j in urdf.joints:
                jt = urdf.joints[j]
                if j in gcfg.external_joints:
                    raise RobotConfigError(f"gripper joint '{j}' is in {src}; remove it from gripper.external_joints")
                if not jt.movable:
                    raise RobotConfigError(f"gripper joint '{j}' is a {jt.type} joint in {src}, not a movable one")
                if jt.mimic is not None:
                    raise RobotConfigError(
                        f"gripper joint '{j}' mimics '{jt.mimic.leader}' in {src}; list the leader '{urdf.mimic_root(j)[0]}' instead"
                    )
            elif j not in gcfg.external_joints:
                raise RobotConfigError(
                    f"gripper joint '{j}' is not a joint of {src}; if its value arrives only in the joint state, "
                    f"give its range under gripper.external_joints"
                )
        for j in gcfg.external_joints:
            if j not in gcfg.joints:
                raise RobotConfigError(f"gripper.external_joints names '{j}', which is not in gripper.joints")
        #: every gripper value read from the joint state, in config order
        self.gripper_joint_names: list[str] = list(gcfg.joints)
        urdf_gripper = [j for j in gcfg.joints if j in urdf.joints]

        # ---- arm joints
        movable = [j.name for j in urdf.joints.values() if j.movable and j.mimic is None]
        path_indep = [j.name for j in self.chain_joints if j.movable and j.mimic is None]
        if config.arm_joints is None:
            arm = [n for n in path_indep if n not in gcfg.joints]
        else:
            arm = list(config.arm_joints)
            for n in arm:
                if n not in urdf.joints:
                    raise RobotConfigError(
                        f"arm joint '{n}' is not a joint of {src} (movable joints: {', '.join(movable)})"
                    )
                jt = urdf.joints[n]
                if not jt.movable:
                    raise RobotConfigError(f"arm joint '{n}' is a {jt.type} joint in {src}, not a movable one")
                if jt.mimic is not None:
                    raise RobotConfigError(f"arm joint '{n}' mimics '{jt.mimic.leader}' in {src}; it cannot be an input")
                if n in gcfg.joints:
                    raise RobotConfigError(f"joint '{n}' is listed both as an arm joint and as a gripper joint")
            missing = [n for n in path_indep if n not in arm and n not in urdf_gripper]
            if missing:
                raise RobotConfigError(
                    f"joint(s) {', '.join(missing)} on the chain {self.base_link} -> {self.ee_link} are not in arm_joints"
                )
        self.arm_joint_names: list[str] = arm
        #: the FK joint vector q: arm joints, then gripper joints that are in the URDF
        self.joint_names: list[str] = arm + urdf_gripper
        self._q_index = {n: i for i, n in enumerate(self.joint_names)}

        # ---- pytorch_kinematics chain from the kinematics-only URDF
        try:
            chain = pk.build_chain_from_urdf(urdf.kinematic_xml())
        except URDFError:
            raise
        except Exception as exc:  # pk's parser raises assorted types
            raise URDFError(f"{src}: pytorch_kinematics could not build the chain ({type(exc).__name__}: {_one_line(exc)})") from None
        self._chain = chain.to(dtype=dtype, device=self.device)  # a fresh chain: to() mutates only ours
        #: False when pytorch_kinematics' internals were not recognised (FK then float32-accurate, ~1e-7)
        self.exact_offsets: bool = _refine_chain_offsets(self._chain, urdf)
        pk_names: list[str] = list(chain.get_joint_parameter_names())
        urdf_movable = [j.name for j in urdf.joints.values() if j.movable]
        if sorted(pk_names) != sorted(urdf_movable):
            raise URDFError(f"{src}: pytorch_kinematics found joints {pk_names}, expected {urdf_movable}")
        self._frame_index: dict[str, int] = dict(chain.frame_to_idx)
        for link in urdf.links:
            if link not in self._frame_index:
                raise URDFError(f"{src}: pytorch_kinematics dropped link '{link}'")
        self.link_names: list[str] = list(urdf.links)

        # th_pk = q @ A^T + b: mimic joints and held joints expressed through q
        A = torch.zeros(len(pk_names), len(self.joint_names), dtype=torch.float64)
        b = torch.zeros(len(pk_names), dtype=torch.float64)
        for i, name in enumerate(pk_names):
            leader, mult, off = urdf.mimic_root(name)
            if leader in self._q_index:
                A[i, self._q_index[leader]] = mult
                b[i] = off
            else:
                b[i] = mult * self._held_value(urdf.joints[leader]) + off
        self._A = A.to(dtype=dtype, device=self.device)
        self._b = b.to(dtype=dtype, device=self.device)
        self.pk_joint_names = pk_names

        # ---- limits of q
        lo, hi = [], []
        for n in self.joint_names:
            jt = urdf.joints[n]
            lo.append(-math.inf if jt.lower is None else jt.lower)
            hi.append(math.inf if jt.upper is None else jt.upper)
        self._lower = torch.tensor(lo, dtype=torch.float64)
        self._upper = torch.tensor(hi, dtype=torch.float64)

        # ---- gripper opening model: opening = offset + values @ w over gripper_joint_names
        self._init_opening(gcfg)

        # ---- control points
        base, side, caxis = control_point_pattern(config.control_points)
        self._cp_base = base.to(dtype=dtype, device=self.device)
        self._cp_side = side.to(dtype=dtype, device=self.device)
        self._cp_axis = caxis.to(dtype=dtype, device=self.device)

    # ------------------------------------------------------------------ setup helpers
    @staticmethod
    def _held_value(j: UrdfJoint) -> float:
        lo = -math.inf if j.lower is None else j.lower
        hi = math.inf if j.upper is None else j.upper
        return float(min(max(0.0, lo), hi))

    def _gripper_limits(self, j: str) -> tuple[float, float]:
        gcfg = self.config.gripper or GripperConfig()
        if j in gcfg.external_joints:
            return gcfg.external_joints[j]
        jt = self.urdf.joints[j]
        if jt.lower is None or jt.upper is None:
            raise RobotConfigError(f"gripper joint '{j}' has no limits in {self.urdf.source}; give gripper.opening.range")
        return jt.lower, jt.upper

    def _init_opening(self, gcfg: GripperConfig) -> None:
        model: OpeningModel = gcfg.opening
        gidx = {n: i for i, n in enumerate(self.gripper_joint_names)}
        w = [0.0] * len(gidx)
        offset = model.offset
        if model.coeffs is None:
            coeffs: dict[str, float] = {}
            for j in self.gripper_joint_names:
                coeffs[j] = 1.0
                if j in self.urdf.joints:
                    for f in self.urdf.mimic_followers(j):
                        coeffs[f] = 1.0
        else:
            coeffs = dict(model.coeffs)
        for j, cval in coeffs.items():
            if j in gidx:
                w[gidx[j]] += cval
                continue
            jt = self.urdf.joints.get(j)
            if jt is not None and jt.mimic is not None:
                leader, mult, off = self.urdf.mimic_root(j)
                if leader in gidx:
                    w[gidx[leader]] += cval * mult
                    offset += cval * off
                    continue
            raise RobotConfigError(
                f"gripper.opening.coeffs names '{j}', which is neither a gripper joint "
                f"({', '.join(self.gripper_joint_names) or 'none'}) nor a URDF mimic of one"
            )
        self._open_w = torch.tensor(w, dtype=torch.float64)
        self._open_offset = float(offset)
        if model.range is not None:
            rng = model.range
        elif self.gripper_joint_names:
            lo = hi = offset
            for j, wj in zip(self.gripper_joint_names, w):
                a, b = self._gripper_limits(j)
                lo += min(wj * a, wj * b)
                hi += max(wj * a, wj * b)
            rng = (lo, hi)
        else:
            rng = (0.0, 0.0)
        if self.gripper_joint_names and not rng[1] > rng[0]:
            raise RobotConfigError(f"gripper opening range {list(rng)} is empty; set gripper.opening.range")
        #: (closed, fully open) opening in metres
        self.opening_range: tuple[float, float] = (float(rng[0]), float(rng[1]))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_config(cls, name_or_path: Union[str, Path], **kwargs) -> "RobotModel":
        """Load ``config/robots/<name>.yaml`` (or a YAML path) and build the model."""
        return cls(load_robot_config(name_or_path), **kwargs)

    def to(self, dtype: Optional[torch.dtype] = None, device: Union[str, torch.device, None] = None) -> "RobotModel":
        """A new model with another dtype/device (this one is left unchanged)."""
        return RobotModel(self.config, dtype=dtype or self.dtype, device=device or self.device)

    # ------------------------------------------------------------------ properties
    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_control_points(self) -> int:
        return self.config.control_points.count

    def joint_limits(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(lower [n_joints], upper [n_joints]) of q in the model dtype; +-inf for continuous joints."""
        return self._lower.to(dtype=self.dtype, device=self.device), self._upper.to(dtype=self.dtype, device=self.device)

    def sample_q(self, n: int, generator: Optional[torch.Generator] = None) -> torch.Tensor:
        """Uniform random configurations within the limits, [n, n_joints] (unbounded joints: [-pi, pi])."""
        lo = torch.where(torch.isfinite(self._lower), self._lower, torch.full_like(self._lower, -math.pi))
        hi = torch.where(torch.isfinite(self._upper), self._upper, torch.full_like(self._upper, math.pi))
        u = torch.rand(n, self.n_joints, generator=generator, dtype=torch.float64)
        return (lo + u * (hi - lo)).to(dtype=self.dtype, device=self.device)

    # ------------------------------------------------------------------ FK
    def _check_q(self, q: torch.Tensor) -> torch.Tensor:
        q = torch.as_tensor(q)
        if q.ndim != 2 or q.shape[1] != self.n_joints:
            raise ValueError(
                f"q must have shape [B, {self.n_joints}] ({', '.join(self.joint_names)}), got {tuple(q.shape)}"
            )
        return q.to(dtype=self.dtype, device=self.device)

    def full_joint_vector(self, q: torch.Tensor) -> torch.Tensor:
        """q [B, n_joints] -> values of every movable URDF joint [B, len(pk_joint_names)] (mimics filled in)."""
        q = self._check_q(q)
        return q @ self._A.T + self._b

    def _fk_all(self, q: torch.Tensor) -> torch.Tensor:
        th = self.full_joint_vector(q)
        T = self._chain.forward_kinematics_tensor(th)  # [F, B, 4, 4] in the URDF root frame
        if self.base_link != self.urdf.root:
            T = _rigid_inverse(T[self._frame_index[self.base_link]]).unsqueeze(0) @ T
        return T

    def fk(self, q: torch.Tensor, links: Optional[Sequence[str]] = None) -> dict[str, torch.Tensor]:
        """Batched FK: q [B, n_joints] -> {link: T_base_link [B, 4, 4]} (all links, or `links`)."""
        names = self.link_names if links is None else list(links)
        for n in names:
            if n not in self._frame_index:
                raise ValueError(f"'{n}' is not a link of robot '{self.urdf.robot_name}'")
        q = self._check_q(q)
        T = self._fk_all(q)
        out = {n: T[self._frame_index[n]] for n in names}
        B = q.shape[0]
        for v in out.values():
            assert v.shape == (B, 4, 4)
        return out

    def ee_pose(self, q: torch.Tensor) -> torch.Tensor:
        """End-effector pose T_base_ee [B, 4, 4] for q [B, n_joints] (paper Eq. T^ee_rob = FK(q))."""
        q = self._check_q(q)
        T = self._fk_all(q)[self._frame_index[self.ee_link]]
        assert T.shape == (q.shape[0], 4, 4)
        return T

    def ee_jacobian(self, q: torch.Tensor) -> torch.Tensor:
        """Geometric Jacobian [B, 6, n_arm] of ``ee_link`` in the base frame for q [B, n_joints]:
        rows 0-2 the linear velocity of its origin, rows 3-5 its angular velocity, per unit rate of
        each arm joint (:attr:`arm_joint_names`); by autograd through the FK, so any URDF works."""
        q = self._check_q(q).detach()
        n = len(self.arm_joint_names)
        with torch.enable_grad():
            qa = q[:, :n].clone().requires_grad_(True)
            T = self.ee_pose(torch.cat([qa, q[:, n:]], dim=1))  # [B, 4, 4]
            p, R = T[:, :3, 3], T[:, :3, :3]
            outs = [p[:, k] for k in range(3)] + [R[:, i, j] for i in range(3) for j in range(3)]
            grads = [torch.autograd.grad(o.sum(), qa, retain_graph=True, allow_unused=True)[0] for o in outs]
        grads = [torch.zeros_like(qa) if g is None else g for g in grads]
        Jp = torch.stack(grads[:3], dim=1)  # [B, 3, n]
        dR = torch.stack(grads[3:], dim=1).reshape(q.shape[0], 3, 3, n)  # dR/dq_j [B, 3, 3, n]
        W = torch.einsum("bikn,bjk->bnij", dR, R.detach())  # dR/dq_j R^T: skew-symmetric [B, n, 3, 3]
        Jw = torch.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], dim=1)  # [B, 3, n]
        J = torch.cat([Jp, Jw], dim=1)
        assert J.shape == (q.shape[0], 6, n)
        return J

    def external_wrench(self, names: Sequence[str], positions: ArrayLike, efforts: ArrayLike) -> torch.Tensor:
        """[T, 6] the wrench on ``ee_link`` (force N, then moment N m about its origin; base frame)
        that best explains the arm joints' external torques: least squares of J^T w = tau.

        ``names`` [J], ``positions``/``efforts`` [T, J] as on /joint_states; ``efforts`` must be
        *external* torques (the arm's own gravity and inertia removed, as a torque-sensing arm's
        estimate gives them, e.g. Franka's ``tau_ext``). Needs at least 6 arm joints (fewer cannot
        determine a wrench: ValueError)."""
        n = len(self.arm_joint_names)
        if n < 6:
            raise ValueError(f"robot '{self.urdf.robot_name}': a wrench needs at least 6 arm joints, it has {n}")
        q = self.q_from_joint_state(names, positions)  # [T, n_joints]
        tau = self._select(names, efforts, self.arm_joint_names, "arm effort").to(q.dtype)  # [T, n]
        J = self.ee_jacobian(q)  # [T, 6, n]
        w = torch.linalg.lstsq(J.transpose(1, 2), tau.unsqueeze(-1)).solution.squeeze(-1)  # [T, 6]
        assert w.shape == (q.shape[0], 6)
        return w

    # ------------------------------------------------------------------ joint states
    def _select(self, names: Sequence[str], positions: ArrayLike, wanted: Sequence[str], what: str) -> torch.Tensor:
        names = [self.config.joint_aliases.get(n, n) for n in names]
        index: dict[str, int] = {}
        for i, n in enumerate(names):
            if n in index:
                raise ValueError(f"joint state names joint '{n}' twice")
            index[n] = i
        pos = torch.as_tensor(np.array(positions, dtype=np.float64) if not torch.is_tensor(positions) else positions)
        if pos.ndim == 0 or pos.shape[-1] != len(names):
            raise ValueError(f"joint state has {len(names)} names but positions of shape {tuple(pos.shape)}")
        missing = [j for j in wanted if j not in index]
        if missing:
            raise ValueError(
                f"joint state is missing {what} joint(s) {', '.join(missing)} (it has: {', '.join(names) or 'none'})"
            )
        sel = pos[..., [index[j] for j in wanted]].to(dtype=self.dtype, device=self.device)
        bad = ~torch.isfinite(sel)
        if bad.any():
            bad_names = [j for k, j in enumerate(wanted) if bad[..., k].any()]
            raise ValueError(f"joint state has non-finite values for {', '.join(bad_names)}")
        return sel

    def q_from_joint_state(self, names: Sequence[str], positions: ArrayLike) -> torch.Tensor:
        """JointState-like (names [J], positions [..., J]) -> q [..., n_joints] in joint_names order.

        Extra joints are ignored, order does not matter, config joint_aliases
        rename message joints; a missing required joint raises ValueError naming it.
        """
        return self._select(names, positions, self.joint_names, "required")

    def gripper_values(self, names: Sequence[str], positions: ArrayLike) -> torch.Tensor:
        """The gripper joint values [..., n_gripper] (gripper_joint_names order) from a joint state."""
        if not self.gripper_joint_names:
            raise ValueError(f"robot '{self.config.name}' has no gripper joints configured")
        return self._select(names, positions, self.gripper_joint_names, "gripper")

    def opening_from_values(self, values: torch.Tensor) -> torch.Tensor:
        """Gripper joint values [..., n_gripper] -> opening in metres [...] (linear opening model)."""
        values = torch.as_tensor(values)
        if values.shape[-1:] != (len(self.gripper_joint_names),):
            raise ValueError(f"gripper values must end in {len(self.gripper_joint_names)}, got {tuple(values.shape)}")
        w = self._open_w.to(dtype=values.dtype if values.is_floating_point() else self.dtype, device=values.device)
        return values.to(w.dtype) @ w + self._open_offset

    def opening_from_q(self, q: torch.Tensor) -> torch.Tensor:
        """Opening [B] from the FK vector q [B, n_joints]; only when all gripper joints are URDF joints."""
        ext = [j for j in self.gripper_joint_names if j not in self._q_index]
        if ext or not self.gripper_joint_names:
            raise ValueError(
                "the gripper opening is not part of q "
                + (f"(external gripper joint(s) {', '.join(ext)})" if ext else "(no gripper joints)")
                + "; pass the opening explicitly"
            )
        q = self._check_q(q)
        return self.opening_from_values(q[:, [self._q_index[j] for j in self.gripper_joint_names]])

    def normalize_opening(self, opening: torch.Tensor) -> torch.Tensor:
        """Opening in metres [...] -> c in [0, 1] (0 closed, 1 fully open), clipped."""
        lo, hi = self.opening_range
        return ((torch.as_tensor(opening) - lo) / (hi - lo)).clamp(0.0, 1.0)

    def gripper_state(self, names: Sequence[str], positions: ArrayLike) -> tuple[torch.Tensor, torch.Tensor]:
        """Joint state -> (opening in metres [...], c in [0, 1] [...]) (the paper's gripper state c_t)."""
        opening = self.opening_from_values(self.gripper_values(names, positions))
        return opening, self.normalize_opening(opening)

    # ------------------------------------------------------------------ control points
    def control_points_ee(self, opening: torch.Tensor) -> torch.Tensor:
        """Control points in the ee frame, [B, P, 3], for openings [B] in metres.

        The opening is clipped to :attr:`opening_range` (a physical jaw cannot
        go beyond it; small negative readings are sensor noise).
        """
        opening = torch.as_tensor(opening, dtype=self.dtype, device=self.device)
        if opening.ndim != 1:
            raise ValueError(f"opening must have shape [B], got {tuple(opening.shape)}")
        lo, hi = self.opening_range
        if self.gripper_joint_names:
            opening = opening.clamp(lo, hi)
        half = 0.5 * opening[:, None, None] * self._cp_side[None, :, None]  # [B, P, 1]
        pts = self._cp_base[None] + half * self._cp_axis
        assert pts.shape == (opening.shape[0], self.n_control_points, 3)
        return pts

    def control_points(self, q: torch.Tensor, opening: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Control points r_j in the robot base frame, [B, P, 3].

        q [B, n_joints]; opening [B] in metres, or None to take it from q
        (only when the gripper joints are URDF joints).
        """
        q = self._check_q(q)
        if opening is None:
            opening = self.opening_from_q(q)
        opening = torch.as_tensor(opening, dtype=self.dtype, device=self.device)
        if opening.shape != (q.shape[0],):
            raise ValueError(f"opening must have shape [{q.shape[0]}], got {tuple(opening.shape)}")
        T = self.ee_pose(q)
        p_ee = self.control_points_ee(opening)
        pts = p_ee @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
        assert pts.shape == (q.shape[0], self.n_control_points, 3)
        return pts


def _origin_matrix(xyz: Sequence[float], rpy: Sequence[float]) -> np.ndarray:
    """URDF <origin>: translation xyz, then fixed-axis roll-pitch-yaw R = Rz(y) Ry(p) Rx(r), float64."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    T = np.eye(4)
    T[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    T[:3, 3] = xyz
    return T


def _refine_chain_offsets(chain, urdf: UrdfModel) -> bool:
    """Replace pytorch_kinematics' joint offsets and axes by float64-exact ones from our parse.

    pytorch_kinematics 0.10 builds every joint origin through float32
    quaternions, so even a float64 chain carries ~1e-7 errors and slightly
    non-orthonormal rotations. We recompute the same quantities (per-frame
    static offset = joint origin, unit joint axes) in float64, check that they
    agree with pytorch_kinematics' own to 1e-5 (a URDFError otherwise: the two
    parsers disagree), and swap them in. Returns False, leaving the chain as
    is, when the chain's internal layout is not the one this was written for.
    """
    static = getattr(chain, "_static_offsets", None)
    axes = getattr(chain, "axes", None)
    idx_to_frame = getattr(chain, "idx_to_frame", None)
    if not (torch.is_tensor(static) and torch.is_tensor(axes) and isinstance(idx_to_frame, dict)):
        return False
    if static.shape != (len(idx_to_frame), 4, 4) or axes.shape != (len(chain.get_joint_parameter_names()), 3):
        return False
    new_static = np.zeros((len(idx_to_frame), 4, 4))
    for f, name in idx_to_frame.items():
        jname = urdf.parent_joint.get(name)
        if jname is None:
            new_static[f] = np.eye(4)
        else:
            j = urdf.joints[jname]
            new_static[f] = _origin_matrix(j.origin_xyz, j.origin_rpy)
    new_axes = np.array([urdf.joints[n].axis for n in chain.get_joint_parameter_names()], dtype=np.float64)
    err_s = float(np.abs(static.detach().cpu().double().numpy() - new_static).max())
    err_a = float(np.abs(axes.detach().cpu().double().numpy() - new_axes).max()) if len(new_axes) else 0.0
    if err_s > 1e-5 or err_a > 1e-5:
        raise URDFError(
            f"{urdf.source}: pytorch_kinematics and our URDF parse disagree on joint origins/axes "
            f"(max difference {max(err_s, err_a):.3g})"
        )
    chain._static_offsets = torch.as_tensor(new_static, dtype=static.dtype, device=static.device)
    if len(new_axes):
        chain.axes = torch.as_tensor(new_axes, dtype=axes.dtype, device=axes.device)
    return True


def _rigid_inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms [..., 4, 4]."""
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out
