"""The live simulator engine behind soma_sim_node, free of rclpy.

:class:`JointStateFilter` validates incoming joint states (names, lengths,
finite values, monotonic stamps), keeps a short history and interpolates by
stamp. :class:`LiveSimulator` owns a :class:`~soma_ros.core.simulator.Simulator`,
the running state, the scene bundle (gravity, table, robot->sim transform,
cameras) and the robot model; it turns a joint vector into the robot action
R_t (control points and gripper state in the simulation frame), steps the
model and renders the cameras (mounted cameras follow FK).

Everything here runs without ROS, so it is unit-tested and benchmarked
directly; the node only moves messages in and out.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Mapping, Optional, Sequence

import numpy as np
import torch

from .core.cameras import Cameras
from .core.effects import near_box
from .core.render import RenderOutput, render
from .core.robot import RobotModel
from .core.scene_bundle import SceneBundle
from .core.simulator import RobotAction, SimState, Simulator
from .core.splats import Splats


_F32_MAX = float(np.finfo(np.float32).max)


class JointStateRejected(ValueError):
    """A joint state that was not used, with the reason."""


class SimulationDiverged(FloatingPointError):
    """A step produced a state that cannot be physical (non-finite, or splats far outside
    the region the object can reach); the state is not taken."""


class JointStateFilter:
    """Validated joint-state history over a fixed set of required joint names.

    ``push`` raises :class:`JointStateRejected` for: names and positions of
    different lengths, duplicate names, missing required joints, non-finite
    values of required joints (or beyond float32's range), stamps older than
    the newest accepted one.
    Unknown extra joints are ignored and order does not matter.

    With ``max_future_s`` set, ``push(..., now_ns=clock)`` also rejects stamps more
    than that far ahead of the receiver's clock: accepted, such a stamp would make
    every later (correctly stamped) message look older and lock the stream out. A
    rejected message never moves the newest stamp that later ones are compared with.

    ``limits`` ({joint: (lower, upper)}, e.g. :func:`joint_limits` of the robot) with
    ``limit_margin`` (joint units: rad or m): positions outside [lower - margin,
    upper + margin] are rejected; joints without an entry are not checked.

    Every call does work bounded by the number of joints, never by the history or the
    message rate. :meth:`count_sequence` counts messages that never arrived (dropped
    upstream because a newer one replaced them) from the publisher's sequence numbers.
    """

    def __init__(self, required: Sequence[str], history: int = 64, max_future_s: Optional[float] = None,
                 limits: Optional[Mapping[str, tuple[float, float]]] = None, limit_margin: float = 0.0) -> None:
        if not required:
            raise ValueError("JointStateFilter needs at least one required joint")
        if limit_margin < 0:
            raise ValueError(f"JointStateFilter: limit_margin must be >= 0, got {limit_margin}")
        self.required = list(required)
        self.max_future_ns = None if max_future_s is None else int(max_future_s * 1e9)
        lim = dict(limits or {})
        self._lo = np.array([lim[r][0] - limit_margin if r in lim else -np.inf for r in self.required])
        self._hi = np.array([lim[r][1] + limit_margin if r in lim else np.inf for r in self.required])
        self.limit_margin = float(limit_margin)
        self._hist: deque[tuple[int, np.ndarray]] = deque(maxlen=history)
        self._lock = threading.Lock()
        self.received = 0
        self.rejected = 0
        self.dropped = 0
        self._last_seq: Optional[int] = None
        self.last_reason = ""

    def count_sequence(self, seq: Optional[int]) -> int:
        """Note a taken message's publication sequence number; returns the messages skipped since
        the previous one (added to ``dropped``). A number that does not increase (another
        publisher, or one that restarted) starts counting afresh and counts nothing."""
        if seq is None or seq <= 0:
            return 0
        gap = 0
        if self._last_seq is not None and seq > self._last_seq:
            gap = seq - self._last_seq - 1
            self.dropped += gap
        self._last_seq = seq
        return gap

    def push(self, names: Sequence[str], positions: Sequence[float], stamp_ns: int,
             now_ns: Optional[int] = None) -> np.ndarray:
        self.received += 1
        try:
            vec = self._validate(names, positions, stamp_ns)
            if now_ns is not None and self.max_future_ns is not None and stamp_ns > now_ns + self.max_future_ns:
                raise JointStateRejected(f"stamp is {(stamp_ns - now_ns) / 1e9:.3f} s ahead of the clock")
        except JointStateRejected as exc:
            self.rejected += 1
            self.last_reason = str(exc)
            raise
        with self._lock:
            self._hist.append((int(stamp_ns), vec))
        return vec

    def _validate(self, names: Sequence[str], positions: Sequence[float], stamp_ns: int) -> np.ndarray:
        if len(names) != len(positions):
            raise JointStateRejected(f"{len(names)} names but {len(positions)} positions")
        index = {}
        for i, n in enumerate(names):
            if n in index:
                raise JointStateRejected(f"duplicate joint name '{n}'")
            index[n] = i
        missing = [r for r in self.required if r not in index]
        if missing:
            raise JointStateRejected(f"missing joints: {', '.join(missing)}")
        vec = np.array([positions[index[r]] for r in self.required], dtype=np.float64)
        # beyond float32's range is infinite for the robot model (float32 FK): such a value
        # would fail every step that samples it
        ok = np.isfinite(vec) & (np.abs(vec) <= _F32_MAX)
        if not np.all(ok):
            bad = [r for r, v in zip(self.required, ok) if not v]
            raise JointStateRejected(f"non-finite values for: {', '.join(bad)}")
        out = (vec < self._lo) | (vec > self._hi)
        if np.any(out):
            i = int(np.flatnonzero(out)[0])
            raise JointStateRejected(
                f"{int(out.sum())} positions outside the joint limits by more than {self.limit_margin:g}: "
                f"{self.required[i]} = {vec[i]:.4g} (allowed {self._lo[i]:.4g}..{self._hi[i]:.4g})")
        with self._lock:
            if self._hist and stamp_ns < self._hist[-1][0]:
                raise JointStateRejected(
                    f"stamp went backwards by {(self._hist[-1][0] - stamp_ns) / 1e6:.1f} ms")
        return vec

    def clear(self) -> None:
        with self._lock:
            self._hist.clear()

    @property
    def has_data(self) -> bool:
        return bool(self._hist)

    def newest_stamp_ns(self) -> Optional[int]:
        with self._lock:
            return self._hist[-1][0] if self._hist else None

    def sample(self, stamp_ns: Optional[int] = None) -> Optional[np.ndarray]:
        """The joint vector at `stamp_ns` (linear interpolation, held at the ends); newest if None."""
        with self._lock:
            if not self._hist:
                return None
            if stamp_ns is None or len(self._hist) == 1 or stamp_ns >= self._hist[-1][0]:
                return self._hist[-1][1].copy()
            if stamp_ns <= self._hist[0][0]:
                return self._hist[0][1].copy()
            stamps = np.fromiter((s for s, _ in self._hist), dtype=np.int64, count=len(self._hist))
            i = int(np.searchsorted(stamps, stamp_ns))
            s0, v0 = self._hist[i - 1]
            s1, v1 = self._hist[i]
        w = 0.0 if s1 == s0 else (stamp_ns - s0) / (s1 - s0)
        return (1 - w) * v0 + w * v1


def joint_limits(robot: RobotModel, names: Sequence[str]) -> dict[str, tuple[float, float]]:
    """{joint: (lower, upper)} for the ``names`` that have limits: the URDF's for its joints
    (continuous joints have none), the gripper config's range for external gripper joints."""
    out: dict[str, tuple[float, float]] = {}
    ext = dict(robot.config.gripper.external_joints) if robot.config.gripper else {}
    for n in names:
        j = robot.urdf.joints.get(n)
        if j is not None and j.type != "continuous" and j.lower is not None and j.upper is not None:
            out[n] = (float(j.lower), float(j.upper))
        elif n in ext:
            lo, hi = ext[n]
            out[n] = (float(min(lo, hi)), float(max(lo, hi)))
    return out


@dataclass
class StepTiming:
    """Wall times in milliseconds of one physics step and of one render of all cameras."""

    step_ms: float = 0.0
    render_ms: float = 0.0


class LiveSimulator:
    """A running rollout: state, scene, robot conditioning and cameras."""

    def __init__(self, sim: Simulator, bundle: SceneBundle, robot: RobotModel,
                 camera_names: Optional[Sequence[str]] = None, render_scale: float = 1.0,
                 max_travel_m: float = 2.0, settle_s: float = 0.0, settle_speed: float = 0.01,
                 passive_friction: Optional[float] = None, passive_exempt_grasped: bool = True) -> None:
        """``max_travel_m``: a step that puts any splat further than this from the initial
        scene's bounding sphere raises :class:`SimulationDiverged` (0 disables the check).
        A tabletop object does not leave a robot's workspace; a learned model driven
        outside its training data can run away at its speed bound instead.

        ``settle_s`` (0 = off) and ``settle_speed`` (m/s): *settling*, the learned-model
        counterpart of a physics engine putting resting bodies to sleep. The model is exactly
        at rest only in the configuration its episode started from (its response there is
        subtracted, see :mod:`soma_ros.core.simulator`); after a manipulation the object lies
        in a new configuration where the network's response is small but not zero, so over
        thousands of steps it creeps. When no robot control point has been within reach of
        the object (the robot effect's radius + 1 cm) and no splat has moved faster than
        ``settle_speed`` for ``settle_s`` seconds of simulated time, the current
        configuration becomes the new initial state (:meth:`Simulator.init_state` on the
        current splats: velocities zero, the reference taken there). The robot coming back
        into reach wakes it as before (its force is a change of the inputs). ``settles``
        counts them; an object still within 10 um of where its episode started is left alone
        (it is at its exact fixed point already).

        ``passive_friction`` (None: the checkpoint's setting, off unless trained with it; a
        number: on, with this friction coefficient; negative: off): the simulator's
        passive-object rule (``DynamicsConfig.passive_friction``, :mod:`soma_ros.core.simulator`).
        Settling stops a slow creep once the object is still; this rule stops the object being
        accelerated away by the learned dynamics in the first place (over repeated grasp cycles
        the ``tiny`` model without it slid the rope 8.9 m in six cycles; see the README).

        ``passive_exempt_grasped`` (with the rule on): steps where the model's own terms act with
        the gripper closed (its robot coupling carrying or dragging the object) are not passive,
        as in the episodes it was trained on (``DynamicsConfig.passive_exempt`` with
        ``passive_exempt_closed``). The rule's friction on top of the learned drag otherwise
        doubles the rope's error while it is manipulated (held-out Chamfer 17.8 -> 11.8 mm for a
        90-iteration model, README "The live node"); with the gripper open the rule still holds,
        or the network lifts a released rope under the hovering gripper. A term fitted after
        training (the discrepancy workflow's named effect, ``EffectSpec.fitted_after_training``) is
        not one of the model's own terms: it was fitted under the rule and stays bounded by it."""
        self.sim = sim.set_passive_friction(passive_friction, sim.trained_terms() if passive_exempt_grasped else [],
                                            True).eval()
        self.max_travel_m = float(max_travel_m)
        if settle_s < 0 or not settle_speed > 0:
            raise ValueError(f"settle_s must be >= 0 and settle_speed > 0, got {settle_s}, {settle_speed}")
        self.settle_steps = int(round(settle_s / float(bundle.dt))) if settle_s > 0 else 0
        self.settle_speed = float(settle_speed)
        self.settles = 0
        self._quiet_steps = 0
        reach = sim.effects.robot_reach()
        self._reach = (reach if reach is not None else 0.05) + 0.01
        self.bundle = bundle
        self.robot = robot
        self.scene = bundle.scene_context()
        self.base_to_sim = bundle.base_to_sim_sim3()
        specs = {c.name: c for c in bundle.cameras}
        names = list(camera_names) if camera_names else list(specs)
        unknown = [n for n in names if n not in specs]
        if unknown:
            raise ValueError(f"unknown camera(s) {', '.join(unknown)}; the scene has {', '.join(specs) or 'none'}")
        self.cameras = [specs[n] for n in names]
        self.render_scale = float(render_scale)
        ext = list(robot.config.gripper.external_joints) if robot.config.gripper else []
        self.required_joints = list(dict.fromkeys(list(robot.joint_names) + list(robot.gripper_joint_names) + ext))
        self._lock = threading.Lock()  # guards (state, template, steps) for readers
        self._sim_lock = threading.Lock()  # one step or reset at a time (they share the bound hierarchy)
        self.template: Splats = bundle.splats
        self.state: Optional[SimState] = None
        self.steps = 0
        self.last_step_cpu_ms = 0.0  # CPU time of the calling thread in the last step
        self.reset(bundle.splats)

    # ------------------------------------------------------------------ scene
    def prepare(self, splats: Splats) -> Optional[tuple]:
        """The hierarchy and static graphs a reset to ``splats`` needs, built without touching the
        running simulator (so a step need not wait for them); None when the splat count is the
        bound one (nothing to build). Pass the result to :meth:`reset`."""
        from .core.graph import build_static_graphs
        from .core.hierarchy import build_hierarchy

        sim = self.sim
        if sim.hierarchy is not None and sim.hierarchy.sizes[0] == len(splats):
            return None
        cfg = sim.config
        with torch.no_grad():
            hier = build_hierarchy(splats.means.detach().cpu().float(), splats.mass.detach().cpu().float(),
                                   cfg.hierarchy.thresholds, cfg.hierarchy.seed_fraction)
            graphs = build_static_graphs(hier.rest_positions, cfg.graph.k, cfg.graph.radii, backend=cfg.graph.knn_backend)
        return hier, graphs

    def reset(self, splats: Splats, prepared: Optional[tuple] = None) -> int:
        """Swap in a new initial scene atomically; returns its splat count. ``prepared``: what
        :meth:`prepare` returned for these splats (built here when not given)."""
        splats.validate()
        sim = self.sim
        with self._sim_lock, torch.no_grad():
            bound = (sim.hierarchy, sim.graphs, sim.splat_attrs)
            try:
                if sim.hierarchy is None or sim.hierarchy.sizes[0] != len(splats):
                    if prepared is not None and prepared[0].sizes[0] == len(splats):
                        sim.bind(splats, *prepared)
                    else:
                        sim.bind(splats)
                state = sim.init_state(splats, self.scene)
            except BaseException:
                # a failure after a rebind must not leave the simulator bound to the new
                # count while the running state is the old scene's
                sim.hierarchy, sim.graphs, sim.splat_attrs = bound
                raise
            m = splats.means.detach().to(state.means.dtype)
            center = m.mean(dim=0)
            radius = float((m - center).norm(dim=-1).max())
            with self._lock:
                self.template = splats
                self.state = state
                self.steps = 0
                self.settles = 0
                self._quiet_steps = 0
                self._bound = (center, radius + self.max_travel_m)
        return len(splats)

    # ------------------------------------------------------------------ robot
    def action(self, joint_vec: np.ndarray) -> RobotAction:
        """Joint vector (``required_joints`` order) -> RobotAction in the sim frame."""
        names = self.required_joints
        pos = torch.as_tensor(joint_vec, dtype=self.robot.dtype)[None]
        q = self.robot.q_from_joint_state(names, pos)
        if self.robot.gripper_joint_names:
            opening, c = self.robot.gripper_state(names, pos)
        else:
            opening, c = torch.zeros(1, dtype=self.robot.dtype), torch.zeros(1, dtype=self.robot.dtype)
        cp = self.robot.control_points(q, opening.reshape(1))[0]
        cp_sim = self.base_to_sim.apply_points(cp)
        cp_sim = torch.as_tensor(cp_sim, dtype=self.sim.dtype)
        return RobotAction(cp_sim, gripper=float(c.reshape(-1)[0]))

    def link_pose_sim(self, joint_vec: np.ndarray, link: str) -> np.ndarray:
        pos = torch.as_tensor(joint_vec, dtype=self.robot.dtype)[None]
        q = self.robot.q_from_joint_state(self.required_joints, pos)
        T_base_link = self.robot.fk(q, links=[link])[link][0].detach().cpu().numpy().astype(np.float64)
        return np.asarray(self.base_to_sim.matrix(), dtype=np.float64) @ T_base_link

    def camera_rig(self, joint_vec: Optional[np.ndarray]) -> Cameras:
        Ks, c2w, names = [], [], []
        w = self.cameras[0].width
        h = self.cameras[0].height
        for c in self.cameras:
            if (c.width, c.height) != (w, h):
                raise ValueError("all rendered cameras must share one image size")
            if c.cam_to_sim is not None:
                T = c.cam_to_sim
            else:
                if joint_vec is None:
                    raise ValueError(f"camera '{c.name}' is mounted on '{c.mount_link}': a joint state is needed")
                T = self.link_pose_sim(joint_vec, c.mount_link) @ c.link_to_cam
            Ks.append(c.K)
            c2w.append(T)
            names.append(c.name)
        cams = Cameras.from_cam_to_world(np.stack(Ks), np.stack(c2w), w, h, names=names)
        return cams.scaled(self.render_scale) if self.render_scale != 1.0 else cams

    # ------------------------------------------------------------------ step
    def step(self, joint_vec: Optional[np.ndarray]) -> tuple[SimState, float]:
        """One physics step from the current state; returns (new state, wall ms).

        The calling thread's CPU time for the step is left in ``last_step_cpu_ms``: wall
        minus CPU is time spent waiting (for the GIL or a core) rather than working."""
        t0 = time.perf_counter()
        c0 = time.thread_time()
        act = self.action(joint_vec) if joint_vec is not None else None
        with self._sim_lock:
            state = self.state
            # inference mode: no autograd bookkeeping on the step's few hundred small ops (about 10 %
            # of a 13k-splat step); the live engine never differentiates through its states
            with torch.inference_mode():
                new = self.sim.step(state, act)
            if not torch.isfinite(new.means).all():
                raise SimulationDiverged("the simulator produced non-finite splat positions")
            if self.max_travel_m > 0:
                center, limit = self._bound
                far = float((new.means.detach() - center).norm(dim=-1).max())
                if far > limit:
                    raise SimulationDiverged(
                        f"a splat is {far - limit + self.max_travel_m:.2f} m outside the initial scene's bounding "
                        f"sphere (limit {self.max_travel_m:.2f} m): the model left the reachable region")
            if self.settle_steps:
                new = self._settle(new, act)
            with self._lock:
                self.state = new
                self.steps += 1
        self.last_step_cpu_ms = (time.thread_time() - c0) * 1e3
        return new, (time.perf_counter() - t0) * 1e3

    def neutral_joint_vec(self) -> np.ndarray:
        """A valid joint vector (``required_joints`` order): the middle of each joint's limits, 0 if unbounded."""
        lo, hi = (t.double().cpu() for t in self.robot.joint_limits())
        mid = torch.where(torch.isfinite(lo) & torch.isfinite(hi), 0.5 * (lo + hi), torch.zeros_like(lo))
        vals = dict(zip(self.robot.joint_names, mid.tolist()))
        return np.array([vals.get(n, 0.0) for n in self.required_joints], dtype=np.float64)

    def calibrate(self, steps: int = 12, renders: int = 3, step_period_s: float = 0.0,
                  render_period_s: float = 0.0) -> StepTiming:
        """The engine's own figures: median wall time of a step and of a render of all cameras,
        measured here with nothing else of the node running. The steps start from the initial
        scene with the robot at :meth:`neutral_joint_vec`; the running state, step count and
        settling counters are restored afterwards (nothing is published).

        With ``step_period_s`` / ``render_period_s`` > 0 the steps / renders start on a grid of
        that period, as the node's loops run them, instead of back to back. The cadence alone
        changes the figure: a step that follows an idle gap costs more CPU than one that follows
        another step, with nothing else running (measured in docs/benchmarks.md, "Live node"),
        so the node compares its in-node times with the engine at its own rates."""
        if steps < 1 or renders < 1:
            raise ValueError(f"calibrate needs steps >= 1 and renders >= 1, got {steps}, {renders}")
        if step_period_s < 0 or render_period_s < 0:
            raise ValueError(f"calibrate needs periods >= 0, got {step_period_s}, {render_period_s}")
        with self._lock:
            saved = (self.state, self.steps, self.settles, self._quiet_steps)
        vec = self.neutral_joint_vec()
        step_ms, render_ms = [], []

        try:
            for _ in paced(step_period_s, steps + 1):  # the first one warms up
                try:
                    _, ms = self.step(vec)
                except (SimulationDiverged, FloatingPointError):
                    with self._lock:
                        self.state = saved[0]
                    _, ms = self.step(None)
                step_ms.append(ms)
            state, template, _ = self.snapshot()
            for _ in paced(render_period_s, renders + 1):
                t0 = time.perf_counter()
                self.render(state, template, vec)
                render_ms.append((time.perf_counter() - t0) * 1e3)
        finally:
            with self._lock:
                self.state, self.steps, self.settles, self._quiet_steps = saved
        return StepTiming(step_ms=float(np.median(step_ms[1:])), render_ms=float(np.median(render_ms[1:])))

    def _settle(self, new: SimState, act: Optional[RobotAction]) -> SimState:
        """Count quiet steps (robot out of reach, every splat slower than ``settle_speed``);
        after ``settle_steps`` of them restart from the current configuration (see __init__)."""
        x = new.means.detach()
        speed = float((new.positions[0] - new.prev_positions[0]).detach().norm(dim=-1).max()) / float(self.scene.dt)
        near = False
        if act is not None and act.control_points.shape[0]:
            cp = act.control_points.to(x.dtype)
            inside = near_box(x, cp, self._reach)  # control points inside the object's box grown by the reach
            if inside.numel():
                near = bool((torch.cdist(cp[inside], x).min() < self._reach).item())
        self._quiet_steps = 0 if (near or speed >= self.settle_speed) else self._quiet_steps + 1
        if self._quiet_steps < self.settle_steps:
            return new
        self._quiet_steps = 0
        rest = new.episode.rest[0].to(new.positions[0].dtype)
        if float((new.positions[0].detach() - rest).abs().max()) < 1e-5:
            return new  # still where its episode started: already an exact fixed point
        self.settles += 1
        with torch.no_grad():
            settled = self.sim.init_state(new.to_splats(self.template), self.scene)
        return dataclasses.replace(settled, control_points=new.control_points)

    def snapshot(self) -> tuple[SimState, Splats, int]:
        with self._lock:
            return self.state, self.template, self.steps

    def render(self, state: SimState, template: Splats, joint_vec: Optional[np.ndarray]) -> tuple[RenderOutput, Cameras]:
        cams = self.camera_rig(joint_vec)
        with torch.no_grad():
            out = render(state.means, state.covs, template.colors().to(state.means.dtype),
                         template.opacities.to(state.means.dtype), cams, background=torch.zeros(3))
        return out, cams

    def current_splats(self) -> Splats:
        state, template, _ = self.snapshot()
        return state.to_splats(template)


def paced(period_s: float, n: int):
    """Yield 0 .. n-1, yield ``k`` no earlier than ``k * period_s`` seconds after the first
    (a grid, so a slow iteration does not shift the later ones; 0: back to back). The live
    engine's calibration and the live benchmark time steps at the node's rate with it."""
    start = time.monotonic()
    for k in range(n):
        wait = start + k * period_s - time.monotonic()
        if period_s > 0 and wait > 0:
            time.sleep(wait)
        yield k


#: ``soma_sim_node`` parameter -> :func:`load_live` keyword, for the engine settings a node
#: parameter sets (names as in ``config/nodes/sim_node.yaml``).
LIVE_PARAMETERS = {"render_scale": "render_scale", "max_object_travel_m": "max_travel_m",
                   "settle_time_s": "settle_s", "settle_speed_mps": "settle_speed",
                   "passive_friction": "passive_friction", "passive_exempt_grasped": "passive_exempt_grasped"}


def live_kwargs(params: Mapping[str, object]) -> dict:
    """:func:`load_live` keywords from node parameter values: every name of
    :data:`LIVE_PARAMETERS` is required, other names are ignored."""
    missing = sorted(set(LIVE_PARAMETERS) - set(params))
    if missing:
        raise KeyError(f"node parameters missing for the live engine: {', '.join(missing)}")
    return {kw: (bool(params[name]) if kw == "passive_exempt_grasped" else float(params[name]))
            for name, kw in LIVE_PARAMETERS.items()}


def load_live(checkpoint: str, scene: str, camera_names: Optional[Sequence[str]] = None,
              render_scale: float = 1.0, device: str = "cpu", max_travel_m: float = 2.0,
              settle_s: float = 0.0, settle_speed: float = 0.01,
              passive_friction: Optional[float] = None, passive_exempt_grasped: bool = True) -> LiveSimulator:
    """Build a LiveSimulator from a checkpoint file and a scene bundle directory."""
    from .core.checkpoint import load_checkpoint

    sim = load_checkpoint(checkpoint, map_location=device)
    bundle = SceneBundle.load(scene)
    robot = RobotModel.from_config(bundle.robot_config)
    return LiveSimulator(sim, bundle, robot, camera_names=camera_names, render_scale=render_scale,
                         max_travel_m=max_travel_m, settle_s=settle_s, settle_speed=settle_speed,
                         passive_friction=passive_friction, passive_exempt_grasped=passive_exempt_grasped)
