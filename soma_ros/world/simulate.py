"""The physics loop of one episode: settle, then follow the plan frame by frame.

The arm is an ideal position-controlled arm: before every physics step its
joint positions and velocities are set to the plan's, so the object can
push on it (contacts, grasp constraints) but never deflect it, and switching
an effect on leaves the joint trajectory bit-for-bit the same. The gripper
is a force-limited position servo, so the fingers stop where the object
stops them. The recorded joint states are the simulator's ``qpos``/``qvel``
after each frame's steps (and ``mj_forward``, so link poses, cameras and flex
vertices are in sync with them). ``effort`` (robot YAML ``effort``) is what a
torque-sensing arm reports after its own gravity model (Franka's estimated
external torque): on every arm joint the generalized force that the world puts
on it through the grasp and the hand's and fingers' contacts (N m; the arm's
own weight is compensated, ``gravcomp``), and on every gripper joint the
servo's force (N; a mimic finger reports its leader's), each plus Gaussian
noise ``effort_noise`` drawn from the episode's own generator (so it never
moves another draw); ``none`` leaves it empty, as on a rig without torque
sensing.

The grasp is a set of ``connect`` equalities from the hand link to the
object vertices nearest the TCP (within ``grasp_radius``), switched on when
the fingers have nearly closed and off when the plan opens the gripper.

An episode whose simulation blows up is rejected, never recorded: MuJoCo's
own divergence warnings, a non-finite state, or an object element stretched
beyond ``physics.max_element_stretch`` times its rest length (a flex that
exploded while MuJoCo kept going; seen once, a rope blown off the table by
the strong wind, stretched 21x after hitting the floor).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import mujoco
import numpy as np

from .config import EFFORT_MODES
from .effects import ActiveEffects
from .planner import Plan
from .robot import gripper_joint_value
from .scene import Scene
from .transforms import MJ_FROM_OPTICAL

__all__ = ["EFFORT_MODES", "FrameState", "EpisodeSim", "element_edges", "max_edge_stretch"]

#: Warnings after which MuJoCo silently resets the state: an episode with one is invalid.
_FATAL_WARNINGS = (mujoco.mjtWarning.mjWARN_BADQACC, mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL)


def element_edges(elements: np.ndarray) -> np.ndarray:
    """The distinct vertex pairs [K, 2] (sorted, i < j) of elements [E, k] (segments, triangles, tets)."""
    e = np.asarray(elements, int)
    if e.ndim != 2 or e.shape[1] < 2:
        raise ValueError(f"element_edges: elements must be [E, k >= 2], got {list(e.shape)}")
    pairs = np.concatenate([e[:, [a, b]] for a in range(e.shape[1]) for b in range(a + 1, e.shape[1])])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def edge_lengths(points: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The lengths [K] of edges [K, 2] for vertex positions [N, 3]."""
    return np.linalg.norm(points[edges[:, 1]] - points[edges[:, 0]], axis=1)


def max_edge_stretch(points: np.ndarray, edges: np.ndarray, rest_length: np.ndarray) -> float:
    """The largest ratio of an edge's length to its rest length [K], for vertex positions [N, 3]."""
    return float(np.max(edge_lengths(points, edges) / np.maximum(rest_length, 1e-12)))


@dataclass
class FrameState:
    """What the recorder needs from one frame.

    ``position``/``velocity`` [n_arm + n_grip] in ``joint_names`` order (rad, m),
    ``effort`` [n_arm + n_grip] (N m, N; module docstring) or [0], ``object_points`` [N, 3] float32 world, ``wrist_T`` [4, 4]
    world <- cam_wrist optical frame (ground truth, for the sidecar).
    """

    index: int
    time: float
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    object_points: np.ndarray
    wrist_T: np.ndarray


class EpisodeSim:
    """Runs one episode's physics. Use :meth:`settle` once, then iterate :meth:`frames`."""

    def __init__(self, scene: Scene, plan: Plan, effects: ActiveEffects, steps_per_frame: int,
                 max_element_stretch: float = 3.0, effort_rng: np.random.Generator | None = None) -> None:
        self.scene = scene
        scene.robot.validate()  # effort / effort_noise
        self._effort_rng = effort_rng if effort_rng is not None else np.random.default_rng(0)
        self.max_element_stretch = float(max_element_stretch)
        geom = scene.geometry
        self._edges = element_edges(geom.elements)
        self._rest_length = edge_lengths(geom.points, self._edges)
        self.plan = plan
        self.effects = effects
        self.spf = steps_per_frame
        self.held: list[int] = []
        self.grasp_log: dict = {}
        self.joint_names = list(scene.robot.arm_joints) + list(scene.robot.gripper.joints)
        rc = scene.robot
        self._grip_q = lambda gap: gripper_joint_value(rc, gap)  # noqa: E731
        self._tcp_local = np.asarray(rc.tcp_offset, float)

    # ------------------------------------------------------------------ control
    def _command(self, i: int) -> None:
        """Gripper servo target for step ``i``."""
        s, p, d = self.scene, self.plan, self.scene.data
        i = min(i, len(p.q_ref) - 1)
        d.ctrl[s.act_grip_pos] = self._grip_q(p.gap_ref[i])
        d.ctrl[s.act_grip_vel] = 0.0

    def _drive_arm(self, i: int, still: bool = False) -> None:
        """Put the arm exactly on the plan at step ``i`` (position and velocity)."""
        s, p, d = self.scene, self.plan, self.scene.data
        i = min(i, len(p.q_ref) - 1)
        d.qpos[s.arm_qadr] = p.q_ref[i]
        d.qvel[s.arm_dadr] = 0.0 if still else p.qd_ref[i]

    def _tcp(self) -> np.ndarray:
        d, h = self.scene.data, self.scene.hand_body
        return d.xpos[h] + d.xmat[h].reshape(3, 3) @ self._tcp_local

    def settle(self, seconds: float) -> None:
        """Put the robot at the plan's first configuration and let the object come to rest."""
        s, d, m = self.scene, self.scene.data, self.scene.model
        d.qpos[s.arm_qadr] = self.plan.q_ref[0]
        gq = self._grip_q(self.plan.gap_ref[0])
        d.qpos[s.grip_qadr] = gq  # the mimic finger starts where its equality wants it
        mujoco.mj_forward(m, d)
        self._command(0)
        for _ in range(int(round(seconds / m.opt.timestep))):
            self._drive_arm(0, still=True)
            mujoco.mj_step(m, d)
        self._drive_arm(0, still=True)
        if not np.all(np.isfinite(d.qpos)):
            raise RuntimeError("simulation diverged while settling (non-finite state)")

    # ------------------------------------------------------------------ grasp
    def _grasp(self) -> None:
        s, m, d = self.scene, self.scene.model, self.scene.data
        mujoco.mj_kinematics(m, d)
        tcp = self._tcp()
        pos = d.xpos[s.vert_body]  # flex vertices sit at their bodies' origins (checked in scene.py)
        dist = np.linalg.norm(pos - tcp, axis=1)
        order = np.argsort(dist)
        chosen = [int(i) for i in order[: s.obj_cfg.grasp_max_vertices] if dist[i] <= s.obj_cfg.grasp_radius]
        R = d.xmat[s.hand_body].reshape(3, 3)
        p = d.xpos[s.hand_body]
        for i in chosen:
            e = s.grasp_eq[i]
            m.eq_data[e, 0:3] = R.T @ (pos[i] - p)  # anchor in the hand frame
            m.eq_data[e, 3:6] = 0.0  # the vertex is its body's origin
            d.eq_active[e] = 1
        self.held = chosen
        self.grasp_log = {
            "time": float(d.time),
            "tcp": tcp.round(5).tolist(),
            "held_vertices": chosen,
            "nearest_distance_m": float(dist[order[0]]),
        }

    def _release(self) -> None:
        s, d = self.scene, self.scene.data
        for i in self.held:
            d.eq_active[s.grasp_eq[i]] = 0
        self.grasp_log["released_time"] = float(d.time)
        self.held = []

    # ------------------------------------------------------------------ loop
    def _effort(self) -> np.ndarray:
        """[n_arm + n_grip] the arm's external joint torques (N m) and the gripper servo's force (N),
        each with the configured noise; [0] with ``effort: none``. Call after ``mj_forward``."""
        s, d, rc = self.scene, self.scene.data, self.scene.robot
        if rc.effort == "none":
            return np.zeros(0)
        arm = d.qfrc_constraint[s.arm_dadr]  # the grasp's and the contacts' generalized force on each arm joint
        servo = float(d.qfrc_actuator[s.grip_dadr[rc.gripper.joints.index(rc.gripper.actuated)]])
        e = np.concatenate([arm, np.full(len(s.grip_dadr), servo)])
        if rc.effort_noise > 0.0:
            e = e + self._effort_rng.normal(0.0, rc.effort_noise, e.shape)
        return e

    def _state(self, k: int) -> FrameState:
        s, m, d = self.scene, self.scene.model, self.scene.data
        mujoco.mj_forward(m, d)
        qadr = np.concatenate([s.arm_qadr, s.grip_qadr])
        dadr = np.concatenate([s.arm_dadr, s.grip_dadr])
        cam = s.camera_ids["cam_wrist"]
        wrist = np.eye(4)
        wrist[:3, :3] = d.cam_xmat[cam].reshape(3, 3) @ MJ_FROM_OPTICAL
        wrist[:3, 3] = d.cam_xpos[cam]
        return FrameState(
            index=k,
            time=k * self.spf * m.opt.timestep,
            position=d.qpos[qadr].copy(),
            velocity=d.qvel[dadr].copy(),
            effort=self._effort(),
            object_points=s.vertex_positions().astype(np.float32),
            wrist_T=wrist,
        )

    def frames(self, n_frames: int) -> Iterator[FrameState]:
        """Yield frame 0 (right after settling), then one frame every ``steps_per_frame`` steps."""
        s, m, d, p = self.scene, self.scene.model, self.scene.data, self.plan
        d.time = 0.0
        yield self._state(0)
        step = 0
        for k in range(1, n_frames):
            for _ in range(self.spf):
                self._drive_arm(step)
                if step == p.grasp_step:
                    self._grasp()
                if p.release_step is not None and step == p.release_step and self.held:
                    self._release()
                self.held = self.effects.maybe_slip(s, step, p.carry, self.held)
                self._command(step + 1)
                self.effects.apply_forces(s, step, p.carry)
                mujoco.mj_step(m, d)
                step += 1
            self._drive_arm(step)
            bad = sum(d.warning[w].number for w in _FATAL_WARNINGS)
            if bad or not np.all(np.isfinite(d.qpos)):
                raise RuntimeError(f"simulation diverged at frame {k} (MuJoCo reset the state or it is non-finite)")
            state = self._state(k)
            stretch = max_edge_stretch(state.object_points.astype(float), self._edges, self._rest_length)
            if stretch > self.max_element_stretch:
                raise RuntimeError(
                    f"simulation diverged at frame {k}: an element of the {s.obj_cfg.kind} is {stretch:.1f}x its rest "
                    f"length (physics.max_element_stretch {self.max_element_stretch:g}); try a smaller "
                    f"physics.timestep or more physics.iterations")
            yield state
