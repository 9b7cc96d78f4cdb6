"""The robot of the reference world: its URDF as a MuJoCo spec, and arm IK.

The URDF is loaded unchanged by MuJoCo's URDF compiler (the same file drives
the learned simulator's FK). Only things outside the file are adjusted here:
mesh paths (``package://`` resolved against the URDF's directory), static-link
fusion switched off (so the hand link exists as a body), collision bits
(only ``contact_links`` touch the object; nothing touches the table), gravity
compensation and the geom colour.
"""

from __future__ import annotations

from dataclasses import dataclass
import mujoco
import numpy as np

from ..core.robot_urdf import resolve_mesh_path
from .config import RobotConfig
from .transforms import so3_log

__all__ = [
    "load_robot_spec",
    "attach_robot",
    "rname",
    "ROBOT_PREFIX",
    "resolve_mesh_path",
    "ArmIK",
    "IKResult",
    "gripper_joint_value",
    "CONTACT_BIT_GRIPPER",
]

#: Prefix of the robot's element names inside the world model.
ROBOT_PREFIX = "robot/"

#: contype bit of gripper geoms; the object's conaffinity includes it, the table's does not.
CONTACT_BIT_GRIPPER = 2


def load_robot_spec(rc: RobotConfig) -> mujoco.MjSpec:
    """The robot's URDF as an :class:`mujoco.MjSpec`, ready to attach to a world."""
    urdf = rc.urdf_path()
    spec = mujoco.MjSpec.from_file(str(urdf))
    spec.compiler.fusestatic = False  # keep fixed-joint links (the hand) as bodies
    spec.compiler.discardvisual = True
    for mesh in spec.meshes:
        mesh.file = str(resolve_mesh_path(mesh.file, urdf.parent))
    bodies = {b.name for b in spec.bodies}
    for link in [rc.base_link, rc.hand_link, rc.wrist_camera.parent, *rc.contact_links]:
        if link not in bodies:
            raise ValueError(f"robot {rc.name}: link '{link}' is not in {urdf.name}")
    joints = {j.name for j in spec.joints}
    for j in [*rc.arm_joints, *rc.gripper.joints]:
        if j not in joints:
            raise ValueError(f"robot {rc.name}: joint '{j}' is not in {urdf.name}")
    base = spec.body(rc.base_link)
    if base.parent.name != "world":
        raise ValueError(f"robot {rc.name}: base_link '{rc.base_link}' is not the URDF's root link")
    contact = set(rc.contact_links)
    for body in spec.bodies:
        if body.name == "world":
            continue
        body.gravcomp = 1.0
        for g in body.geoms:
            g.rgba = list(rc.rgba)
            if body.name in contact:
                g.contype = CONTACT_BIT_GRIPPER
                g.conaffinity = 0
                g.condim = 3
                g.friction = [1.0, 0.005, 0.0001]
                g.solref = [0.005, 1.0]
                g.solimp = [0.95, 0.99, 0.001, 0.5, 2.0]
            else:
                g.contype = 0
                g.conaffinity = 0
    return spec


def attach_robot(world: mujoco.MjSpec, robot: mujoco.MjSpec, pos: np.ndarray, quat: np.ndarray) -> None:
    """Attach the robot spec under a frame at ``pos``/``quat`` (w, x, y, z).

    Element names get :data:`ROBOT_PREFIX` (MuJoCo-internal only; use :func:`rname`).
    """
    frame = world.worldbody.add_frame(pos=list(map(float, pos)), quat=list(map(float, quat)))
    world.attach(robot, frame=frame, prefix=ROBOT_PREFIX)


def rname(name: str) -> str:
    """MuJoCo name of a URDF link/joint once the robot is attached."""
    return ROBOT_PREFIX + name


@dataclass
class IKResult:
    q: np.ndarray  # [n_arm] radians
    pos_err: float  # metres
    rot_err: float  # radians
    iterations: int


class ArmIK:
    """Damped-least-squares IK of the TCP pose on a robot-only MuJoCo model.

    The model is the same URDF attached at the same base pose as in the world,
    so its kinematics are identical. ``solve`` returns arm joint values whose
    TCP (``tcp_offset`` in the hand link) reaches a world position and whose
    hand orientation reaches a world rotation [3, 3]; a null-space term pulls
    the redundant joints towards ``rest_posture``.
    """

    def __init__(self, rc: RobotConfig, base_pos: np.ndarray, base_quat: np.ndarray) -> None:
        world = mujoco.MjSpec()
        attach_robot(world, load_robot_spec(rc), base_pos, base_quat)
        self.model = world.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.jnt_ids = [m.joint(rname(n)).id for n in rc.arm_joints]
        self.qadr = np.array([m.jnt_qposadr[j] for j in self.jnt_ids])
        self.dadr = np.array([m.jnt_dofadr[j] for j in self.jnt_ids])
        self.lo = np.array([m.jnt_range[j][0] for j in self.jnt_ids])
        self.hi = np.array([m.jnt_range[j][1] for j in self.jnt_ids])
        limited = np.array([m.jnt_limited[j] for j in self.jnt_ids], bool)
        self.lo[~limited], self.hi[~limited] = -np.pi * 2, np.pi * 2
        self.hand = m.body(rname(rc.hand_link)).id
        self.tcp_local = np.asarray(rc.tcp_offset, float)
        self.rest = np.asarray(rc.rest_posture, float) if rc.rest_posture else (self.lo + self.hi) / 2.0
        self._jp = np.zeros((3, m.nv))
        self._jr = np.zeros((3, m.nv))

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """TCP position [3] and hand rotation [3, 3] in the world for arm joints ``q``."""
        d = self.data
        d.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, d)
        R = d.xmat[self.hand].reshape(3, 3).copy()
        return d.xpos[self.hand] + R @ self.tcp_local, R

    def solve(
        self,
        pos: np.ndarray,
        rot: np.ndarray,
        q0: np.ndarray,
        max_iter: int = 100,
        tol_pos: float = 1e-5,
        tol_rot: float = 1e-4,
        damping: float = 1e-3,
        null_gain: float = 0.1,
    ) -> IKResult:
        m, d = self.model, self.data
        q = np.clip(np.asarray(q0, float).copy(), self.lo, self.hi)
        it = 0
        for it in range(1, max_iter + 1):
            p, R = self.fk(q)
            e_p = pos - p
            e_r = R @ so3_log(R.T @ rot)  # world-frame rotation error
            if np.linalg.norm(e_p) < tol_pos and np.linalg.norm(e_r) < tol_rot:
                break
            mujoco.mj_comPos(m, d)
            mujoco.mj_jac(m, d, self._jp, self._jr, p, self.hand)
            J = np.vstack([self._jp[:, self.dadr], self._jr[:, self.dadr]])
            e = np.concatenate([e_p, e_r])
            JJt = J @ J.T + (damping**2) * np.eye(6)
            dq = J.T @ np.linalg.solve(JJt, e)
            Jpinv = J.T @ np.linalg.inv(JJt)
            dq += (np.eye(len(q)) - Jpinv @ J) @ (null_gain * (self.rest - q))
            n = np.linalg.norm(dq)
            if n > 0.3:
                dq *= 0.3 / n
            q = np.clip(q + dq, self.lo, self.hi)
        p, R = self.fk(q)
        return IKResult(
            q=q,
            pos_err=float(np.linalg.norm(pos - p)),
            rot_err=float(np.linalg.norm(so3_log(R.T @ rot))),
            iterations=it,
        )


def gripper_joint_value(rc: RobotConfig, gap: float) -> float:
    """Actuated gripper joint value for a finger gap (metres)."""
    return rc.gripper.joint_offset + rc.gripper.joint_per_width * gap
