"""Benchmark of the live simulator node (soma_sim_node) over real ROS 2 topics.

Usage::

    python -m benchmarks.bench_live [--splats 13000] [--width 320 --height 240] [--cameras 1 3]
                                    [--trials 20] [--sustain-s 20] [--long-steps 10000]
                                    [--flood-s 30] [--flood-hz 1000] [--long-run TRAINED_RUN]
                                    [--only engine latency rates long flood] [--json OUT.json]

The node runs as its own OS process (``python -m soma_ros.nodes.sim_node``) on
a random-weight ``cpu`` model bound to a synthetic rope of ``--splats`` splats
(the node's cost does not depend on the weights), with ``cam_front`` (a fixed
camera) as its only camera. This process plays the robot: it publishes
``/joint_states`` from its own rclpy context and listens to the node's
topics. Sections:

``engine``   the node's work without ROS, in this process with one torch thread and the
             node's settings (``config/nodes/sim_node.yaml`` with ``--param``): CPU
             time (and wall time) per physics step (back to back, and at the node's
             ``--rate-hz`` as the node runs them), per render, per splat cloud,
             and the cores the node needs at the target rates -- a figure that holds
             on a shared machine, where the ROS sections below depend on how much CPU
             the other users leave.
``latency``  end-to-end latency from a /joint_states message to the first image
             it causes. The scene is reset, the gripper hovers just out of the
             robot effect's reach (the untrained model then keeps the rope
             bit-exactly still, so every image equals a baseline image), and one
             message moves the gripper into the rope. The time from publishing
             that message to receiving the first ``image_raw`` whose pixels
             differ from the baseline is the latency: it covers the wait for the
             next physics tick, the step that consumes the message, the wait for
             the next render tick, the render, the conversion and the transport.
             Nothing else can change the image, so the measure is causal, not a
             correlation of stamps. Repeated ``--trials`` times.
``rates``    for each camera count of ``--cameras`` (1: ``cam_front``; 3: with two more
             fixed cameras, ``cam_left`` and ``cam_right``, added to the scene bundle):
             sustained step rate and image-set rate for ``--sustain-s`` seconds while
             joint states stream at 100 Hz moving the gripper back and forth along
             the rope just above the robot effect's reach (so the rope stays at
             rest and fully in view: the render pays for every splat; a random
             model would throw a touched rope out of view and make rendering
             look cheap), as reported in /soma/status (rates over the node's 1 s
             window) and as counted here (image sets received / s -- the slowest
             camera's count --, status.step / s), and the node's median step and
             render times (wall and CPU) against the engine's, which the node measures
             alone at start-up at its own step and image rates and reports in
             /soma/status (with ``engine`` in the same run: also against the same sweep
             stepped here, back to back and at the node's rate).
             The node's, this process's and the rest of the machine's CPU use are
             reported with every section (the cores may be shared).
``long``     a ``--long-steps`` live run at a high ``rate_hz`` with images off while
             the gripper repeatedly grasps and lifts at the rope (``--long-run RUN``:
             on a trained run instead of the untrained model); the last
             /soma/splats is checked: finite, max displacement from the initial
             scene, and the object's extent (max distance from its centroid)
             against the initial one (a drift explosion would blow the extent up).
``flood``    ``--flood-hz`` /joint_states for ``--flood-s`` seconds (1 in 10
             with a NaN value); node RSS (psutil) before, during and after;
             received / rejected counters from /soma/status; step rate during it.

Every child process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and its own
ROS_DOMAIN_ID. The module also holds the pure helpers the tests share
(:class:`Poser`: inverse kinematics for gripper trajectories; :func:`extent`) and
:class:`LiveProbe`, the robot side of a node under test (rclpy imported lazily).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch

__all__ = ["Poser", "LiveProbe", "extent", "grasp_trajectory", "PANDA_EXTRA_JOINTS", "main"]

#: Joints a real Panda publishes beyond the ones the simulator needs (the mimic finger).
PANDA_EXTRA_JOINTS = ("panda_finger_joint2",)


# --------------------------------------------------------------------------- kinematics
class Poser:
    """Joint vectors that put the gripper where a test wants it (numerical IK on the robot model).

    The target is the TCP -- the mean of the robot's control points -- at a point of
    the simulation frame, with the hand's approach axis along gravity (pointing
    down) and the fingers closing along ``closing`` (a horizontal axis of the
    simulation frame). Solved with L-BFGS on the model's FK, warm-started from
    ``q0``. Returns joint vectors in ``names`` order (the LiveSimulator's
    ``required_joints``).
    """

    def __init__(self, robot, base_to_sim: np.ndarray, names: Sequence[str],
                 gravity: Sequence[float] = (0.0, 0.0, -9.81)) -> None:
        self.robot = robot
        self.names = list(names)
        M = np.asarray(base_to_sim, dtype=np.float64)
        A = M[:3, :3]
        self.scale = float(np.cbrt(abs(np.linalg.det(A))))
        self.R_b2s = A / self.scale
        self.t_b2s = M[:3, 3]
        g = np.asarray(gravity, dtype=np.float64)
        self.down = g / np.linalg.norm(g)
        self.grip_names = list(robot.gripper_joint_names)
        self.arm_idx = [i for i, n in enumerate(robot.joint_names) if n not in self.grip_names]
        self.grip_idx = [i for i, n in enumerate(robot.joint_names) if n in self.grip_names]
        lo, hi = robot.joint_limits()
        mid = torch.where(torch.isfinite(lo) & torch.isfinite(hi), 0.5 * (lo + hi), torch.zeros_like(lo))
        self.q_default = mid.double().numpy()
        if robot.config.name == "panda":  # a comfortable "ready" pose: hand down in front of the base
            self.q_default[self.arm_idx] = [0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785]

    def base_point(self, p_sim: Sequence[float]) -> np.ndarray:
        return self.R_b2s.T @ ((np.asarray(p_sim, dtype=np.float64) - self.t_b2s) / self.scale)

    def solve(self, tcp_sim: Sequence[float], finger: float = 0.04, closing: Sequence[float] = (0.0, 1.0, 0.0),
              q0: Optional[np.ndarray] = None, iters: int = 60) -> np.ndarray:
        """Joint vector ([len(names)], float64) with the TCP at `tcp_sim` (gripper joints at `finger`)."""
        robot = self.robot
        target = torch.tensor(self.base_point(tcp_sim), dtype=torch.float64)
        z = self.R_b2s.T @ self.down
        y = self.R_b2s.T @ np.asarray(closing, dtype=np.float64)
        y = y - z * (y @ z)
        y /= np.linalg.norm(y)
        R_t = torch.tensor(np.stack([np.cross(y, z), y, z], axis=1), dtype=robot.dtype)
        q_full = torch.tensor(self.q_default if q0 is None else self._q_from_vec(q0), dtype=robot.dtype)
        q_full[self.grip_idx] = float(finger)
        arm = q_full[self.arm_idx].clone().requires_grad_(True)
        opening = robot.opening_from_values(torch.full((1, len(self.grip_names)), float(finger), dtype=robot.dtype)) \
            if self.grip_names else torch.zeros(1, dtype=robot.dtype)
        opening = opening.reshape(1)
        tgt = target.to(robot.dtype)

        def full(a):
            q = q_full.clone()
            q[self.arm_idx] = a
            return q[None]

        opt = torch.optim.LBFGS([arm], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            q = full(arm)
            cp = robot.control_points(q, opening)[0]
            R = robot.ee_pose(q)[0, :3, :3]
            loss = 100.0 * ((cp.mean(0) - tgt) ** 2).sum() + 0.1 * ((R - R_t) ** 2).sum()
            loss.backward()
            return loss

        opt.step(closure)
        with torch.no_grad():
            q = full(arm.detach())
            err = float((robot.control_points(q, opening)[0].mean(0) - tgt).norm()) * self.scale
        if err > 2e-3:
            raise RuntimeError(f"IK: TCP {list(tcp_sim)} missed by {err * 1e3:.1f} mm (unreachable?)")
        return self._vec_from_q(q[0].double().numpy())

    def _q_from_vec(self, vec: np.ndarray) -> np.ndarray:
        index = {n: i for i, n in enumerate(self.names)}
        return np.array([vec[index[n]] for n in self.robot.joint_names], dtype=np.float64)

    def _vec_from_q(self, q: np.ndarray) -> np.ndarray:
        index = {n: i for i, n in enumerate(self.robot.joint_names)}
        return np.array([q[index[n]] for n in self.names], dtype=np.float64)

    def line(self, a: Sequence[float], b: Sequence[float], n: int, finger: float = 0.04,
             q0: Optional[np.ndarray] = None, closing: Sequence[float] = (0.0, 1.0, 0.0)) -> list[np.ndarray]:
        """n joint vectors moving the TCP from a to b in a straight line (warm-started IK)."""
        out, q = [], q0
        for s in np.linspace(0.0, 1.0, n):
            q = self.solve((1 - s) * np.asarray(a, float) + s * np.asarray(b, float), finger, closing, q0=q,
                           iters=60 if q is None else 25)
            out.append(q)
        return out

    def with_finger(self, vec: np.ndarray, finger: float) -> np.ndarray:
        v = np.array(vec, dtype=np.float64)
        for n in self.grip_names:
            v[self.names.index(n)] = finger
        return v


def grasp_trajectory(poser: Poser, grasp: Sequence[float], lift: float = 0.10, above: float = 0.12,
                     steps: int = 30, open_finger: float = 0.04, closed_finger: float = 0.0,
                     closing: Sequence[float] = (0.0, 1.0, 0.0)) -> list[np.ndarray]:
    """Approach from `above` m over `grasp` with the gripper open, descend, close, lift by `lift`.

    Returns the joint vectors at the simulation rate (``steps`` per segment, closing over
    steps // 2, then a short hold at the top).
    """
    g = np.asarray(grasp, dtype=np.float64)
    up = -poser.down
    path = poser.line(g + above * up, g, steps, finger=open_finger, closing=closing)
    bottom = path[-1]
    path += [poser.with_finger(bottom, open_finger + (closed_finger - open_finger) * s)
             for s in np.linspace(0.0, 1.0, max(2, steps // 2))]
    path += poser.line(g, g + lift * up, steps, finger=closed_finger, q0=bottom, closing=closing)
    path += [path[-1]] * (steps // 2)
    return path


def object_grasp(points: np.ndarray, down: np.ndarray, at: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """(grasp point, closing axis) for an elongated object: a point `at` along its principal
    horizontal axis (at the median height), fingers closing across that axis."""
    p = np.asarray(points, dtype=np.float64)
    c = p.mean(0)
    d = p - c
    d_h = d - np.outer(d @ down, down)
    _, _, vt = np.linalg.svd(d_h, full_matrices=False)
    axis = vt[0]
    u = d_h @ axis
    lo, hi = np.percentile(u, 1), np.percentile(u, 99)
    target = c + (lo + at * (hi - lo)) * axis
    # the splats nearest that point along the axis give its height and lateral position
    near = np.abs(u - (lo + at * (hi - lo))) < 0.01 * max(hi - lo, 1e-6) + 0.005
    grasp = np.median(p[near], axis=0) if near.any() else target
    closing = np.cross(down, axis)
    return grasp, closing / np.linalg.norm(closing)


def extent(points: np.ndarray) -> float:
    """Max distance of points [N, 3] from their centroid (the object's size)."""
    p = np.asarray(points, dtype=np.float64)
    return float(np.linalg.norm(p - p.mean(0), axis=1).max())


# --------------------------------------------------------------------------- the robot side over ROS
class LiveProbe:
    """The robot side of a soma_sim_node: publishes /joint_states and hears the node's topics.

    Lives in the caller's rclpy ``context`` (its own domain); everything arrives through
    :meth:`spin_until`, which spins this probe's executor until a predicate holds or a
    deadline passes. Keeps the newest message of each topic with its receive time
    (``time.monotonic()``), counts per topic, and every /soma/status (bounded).
    ``on_image(camera, msg, t_recv)`` is called for each image when set.
    """

    def __init__(self, context, names: Sequence[str], prefix: str = "/soma",
                 cameras: Sequence[str] = ("cam_front",), depth: bool = False, info: bool = False,
                 splats: bool = True, extra_joints: Sequence[str] = PANDA_EXTRA_JOINTS, tf_static: bool = False) -> None:
        from collections import deque

        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image, JointState, PointCloud2
        from soma_msgs.msg import SimStatus
        from soma_msgs.srv import ResetScene

        self._JointState = JointState
        self.names = list(names)
        self.extra = list(extra_joints)
        self.node = rclpy.create_node(f"soma_probe_{os.getpid()}", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.node.create_publisher(JointState, "/joint_states", QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.latest: dict = {}
        self.t_latest: dict = {}
        self.count: dict = {}
        self.status: deque = deque(maxlen=20000)
        self.on_image: Optional[Callable] = None
        self.published = 0

        def keep(key):
            def cb(msg):
                t = time.monotonic()
                self.latest[key], self.t_latest[key] = msg, t
                self.count[key] = self.count.get(key, 0) + 1
                if key[0] == "image" and self.on_image is not None:
                    self.on_image(key[1], msg, t)
                if key == ("status",):
                    self.status.append((t, msg))
            return cb

        p = prefix.rstrip("/")
        for cam in cameras:
            self.node.create_subscription(Image, f"{p}/{cam}/image_raw", keep(("image", cam)), reliable)
            if depth:
                self.node.create_subscription(Image, f"{p}/{cam}/depth", keep(("depth", cam)), reliable)
            if info:
                self.node.create_subscription(CameraInfo, f"{p}/{cam}/camera_info", keep(("info", cam)), reliable)
        if splats:
            self.node.create_subscription(PointCloud2, f"{p}/splats", keep(("splats",)), reliable)
        self.node.create_subscription(SimStatus, f"{p}/status", keep(("status",)), QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        if tf_static:
            from tf2_msgs.msg import TFMessage

            self.node.create_subscription(TFMessage, "/tf_static", keep(("tf_static",)), QoSProfile(
                depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.reset_client = self.node.create_client(ResetScene, f"{p}/reset")
        self._ResetScene = ResetScene

    # ---------------------------------------------------------------- helpers
    def now_ns(self) -> int:
        return self.node.get_clock().now().nanoseconds

    def spin_until(self, predicate: Callable[[], bool], timeout: float) -> bool:
        from soma_ros.nodes.testing import spin_until

        return spin_until(self.executor, predicate, timeout, step=0.01)

    def spin_for(self, seconds: float) -> None:
        """Spin (handle arriving messages) for `seconds`; for pacing, not for waiting on a condition."""
        self.spin_until(lambda: False, seconds)

    def joint_msg(self, vec: Sequence[float], stamp_ns: Optional[int] = None, names: Optional[Sequence[str]] = None,
                  positions: Optional[Sequence[float]] = None):
        """A JointState: `vec` in ``names`` order plus the robot's extra joints (mimic finger = finger 1)."""
        msg = self._JointState()
        ns = self.now_ns() if stamp_ns is None else int(stamp_ns)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
        if names is not None:
            msg.name, msg.position = list(names), [float(v) for v in positions]
            return msg
        vals = [float(v) for v in vec]
        fill = vals[self.names.index("panda_finger_joint1")] if "panda_finger_joint1" in self.names else 0.0
        msg.name = self.names + self.extra
        msg.position = vals + [fill] * len(self.extra)
        msg.velocity = [0.0] * len(msg.name)
        return msg

    def publish(self, vec: Sequence[float] = (), stamp_ns: Optional[int] = None, **raw) -> None:
        self.pub.publish(self.joint_msg(vec, stamp_ns, **raw))
        self.published += 1

    def play(self, path: Sequence[np.ndarray], hz: float = 30.0, until: Optional[Callable[[], bool]] = None) -> None:
        """Publish joint vectors at `hz` (stamped now), spinning in between."""
        t_next = time.monotonic()
        for v in path:
            self.publish(v)
            t_next += 1.0 / hz
            self.spin_until(lambda: time.monotonic() >= t_next, 1.0 / hz + 0.5)
            if until is not None and until():
                return

    def play_stepped(self, path: Sequence[np.ndarray], timeout: float = 10.0) -> int:
        """Publish each joint vector once and wait for a physics step that used it.

        A step used the message stamped ``s`` when its status says ``stamp - lag == s``
        (the node samples the newest joint state and reports its age). So every pose
        drives (at least) one step whatever the node's step rate: a replay at the
        simulation's pace, as offline. Returns how many steps were waited for.
        """
        n = 0
        for v in path:
            stamp = self.now_ns()
            self.publish(v, stamp_ns=stamp)

            def used() -> bool:
                st = self.last_status()
                if st is None:
                    return False
                t = st.header.stamp.sec * 10**9 + st.header.stamp.nanosec
                return abs(t - st.joint_state_lag_ms * 1e6 - stamp) < 1e5 or t - st.joint_state_lag_ms * 1e6 > stamp + 1e5

            if not self.spin_until(used, timeout):
                raise TimeoutError("no physics step used the published joint state")
            n += 1
        return n

    def hold(self, vec: Sequence[float], until: Callable[[], bool], timeout: float, hz: float = 30.0) -> bool:
        """Publish `vec` at `hz` (stamped now) until `until()` holds or `timeout` s pass; returns until()."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.publish(vec)
            t_next = min(time.monotonic() + 1.0 / hz, deadline)
            if self.spin_until(lambda: until() or time.monotonic() >= t_next, 1.0 / hz + 0.5) and until():
                return True
        return until()

    def last(self, *key):
        return self.latest.get(tuple(key))

    def last_status(self):
        return self.latest.get(("status",))

    def wait_for(self, *key, after: Optional[int] = None, timeout: float = 30.0):
        """The next message on `key` (after count `after`, default: the current count)."""
        n0 = self.count.get(tuple(key), 0) if after is None else after
        ok = self.spin_until(lambda: self.count.get(tuple(key), 0) > n0, timeout)
        return self.latest[tuple(key)] if ok else None

    def reset(self, splats_msg=None, ply_path: str = "", initial_joint_state=None, timeout: float = 60.0):
        if not self.reset_client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError("the reset service did not appear")
        req = self._ResetScene.Request()
        if splats_msg is not None:
            req.splats = splats_msg
        req.ply_path = ply_path
        if initial_joint_state is not None:
            req.initial_joint_state = initial_joint_state
        fut = self.reset_client.call_async(req)
        if not self.spin_until(fut.done, timeout):
            raise TimeoutError("no answer from the reset service")
        return fut.result()

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def rss_mb(pid: int) -> float:
    import psutil

    return psutil.Process(pid).memory_info().rss / 2**20


def cloud_means(msg) -> np.ndarray:
    from soma_ros.core.cloud_layout import points_from_cloud

    return points_from_cloud(msg).astype(np.float64)


# --------------------------------------------------------------------------- the benchmark
EXTRA_CAMERAS = ("cam_left", "cam_right")


def with_cameras(scene_dir: Path, n_cams: int, out_dir: Path) -> tuple[Path, list[str]]:
    """A copy of the scene bundle with ``n_cams`` fixed cameras: its first fixed camera and up
    to two more at the same distance from the object's centroid, turned +-50 degrees about the
    gravity axis (same intrinsics and image size). Returns (bundle folder, camera names)."""
    from soma_ros.core.cameras import look_at
    from soma_ros.core.scene_bundle import CameraSpec, SceneBundle

    if not 1 <= n_cams <= 1 + len(EXTRA_CAMERAS):
        raise ValueError(f"--cameras: 1 to {1 + len(EXTRA_CAMERAS)} cameras, got {n_cams}")
    b = SceneBundle.load(scene_dir)
    first = next(c for c in b.cameras if c.cam_to_sim is not None)
    if n_cams == 1:
        return Path(scene_dir), [first.name]
    centre = b.splats.means.detach().double().mean(0).numpy()
    up = -np.asarray(b.gravity, dtype=np.float64)
    up /= np.linalg.norm(up)
    eye = first.cam_to_sim[:3, 3] - centre
    cams = [first]
    for name, ang in zip(EXTRA_CAMERAS[: n_cams - 1], (math.radians(50), math.radians(-50))):
        # Rodrigues rotation of the front camera's offset about the up axis
        e = (eye * math.cos(ang) + np.cross(up, eye) * math.sin(ang) + up * (up @ eye) * (1 - math.cos(ang)))
        c2w = look_at(centre + e, centre, up=up, dtype=torch.float64).numpy()
        cams.append(CameraSpec(name, first.width, first.height, first.K, cam_to_sim=c2w))
    b.cameras = cams + [c for c in b.cameras if c is not first]
    b.save(out_dir)
    return out_dir, [c.name for c in cams]


def machine_line(torch_threads: int) -> str:
    """The machine line with the node's torch threads (the process measured) and the Python version."""
    from soma_ros.core.machine import machine_description

    return f"{machine_description(torch_threads=torch_threads)} | Python {sys.version.split()[0]}"


def load_line() -> str:
    l1, l5, l15 = os.getloadavg()
    return f"load average {l1:.2f} {l5:.2f} {l15:.2f} on {os.cpu_count()} cores"


class _Bench:
    """One node process + the probe, for one section."""

    def __init__(self, run, params: Sequence[str], names: Sequence[str], cameras: Sequence[str], splats: bool) -> None:
        import rclpy
        from rclpy.context import Context

        from soma_ros.nodes.testing import RosProcess, ros_env, unique_domain_id

        self.domain = unique_domain_id()
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        os.environ["ROS_DOMAIN_ID"] = str(self.domain)
        self.ctx = Context()
        rclpy.init(args=[], context=self.ctx, domain_id=self.domain)  # not the benchmark's own argv
        args = ["--ros-args", "-p", f"checkpoint:={run[0]}", "-p", f"scene:={run[1]}"]
        for p in params:
            args += ["-p", p]
        self.node = RosProcess("soma_ros.nodes.sim_node", args, ros_env(self.domain), name="bench_sim_node")
        self.probe = LiveProbe(self.ctx, names, cameras=cameras, splats=splats)

    def started(self, vec, key, timeout: float = 180.0) -> None:
        ok = self.probe.hold(vec, lambda: (self.probe.count.get(key, 0) > 0 and self.probe.last_status() is not None)
                             or not self.node.alive(), timeout)
        if not (ok and self.node.alive()):
            raise RuntimeError(f"soma_sim_node did not start:\n{self.node.output()[-4000:]}")

    def close(self) -> str:
        import rclpy

        out = self.node.output()
        self.node.stop()
        self.probe.close()
        if self.ctx.ok():
            rclpy.shutdown(context=self.ctx)
        return out


class CpuMeter:
    """CPU use over a window: the node process (with its threads and its child processes, such as
    the render process), this process, and the rest of the machine (other users of the shared
    cores), in cores (1.0 = one core busy)."""

    def __init__(self, node_pid: int) -> None:
        import psutil

        self.node = psutil.Process(node_pid)
        self.kids = self.node.children(recursive=True)
        self.me = psutil.Process()
        self.t0 = time.monotonic()
        self.n0, self.m0 = self._tree(), self._cpu(self.me)
        self.s0 = psutil.cpu_times()

    def _tree(self) -> float:
        import psutil

        total = self._cpu(self.node)
        for k in self.kids:
            try:
                total += self._cpu(k)
            except psutil.Error:
                pass
        return total

    @staticmethod
    def _cpu(p) -> float:
        t = p.cpu_times()
        return t.user + t.system + getattr(t, "children_user", 0.0) + getattr(t, "children_system", 0.0)

    def stop(self) -> dict:
        import psutil

        dt = time.monotonic() - self.t0
        s1 = psutil.cpu_times()
        busy = (sum(s1) - s1.idle - getattr(s1, "iowait", 0.0)) - (sum(self.s0) - self.s0.idle - getattr(self.s0, "iowait", 0.0))
        node = (self._tree() - self.n0) / dt
        me = (self._cpu(self.me) - self.m0) / dt
        return {"node_cores": node, "probe_cores": me, "others_cores": max(0.0, busy / dt - node - me),
                "cores": os.cpu_count()}


def _cpu_text(c: dict) -> str:
    return (f"CPU: node {c['node_cores']:.2f}, probe {c['probe_cores']:.2f}, "
            f"others {c['others_cores']:.2f} of {c['cores']} cores")


def _pct(xs: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs, dtype=np.float64), q)) if len(xs) else float("nan")


def _rgb(msg) -> np.ndarray:
    return np.frombuffer(bytes(msg.data), np.uint8)


def bench_latency(b: _Bench, scene_dir: str, hover, in_rope, trials: int, say) -> dict:
    """Causal latency: gripper from just out of reach into the rope by one message -> first changed image."""
    p = b.probe
    baseline: dict = {}
    lat, changed_px, waits = [], [], []
    state = {"t_pub": None, "hit": None}

    def on_image(cam, msg, t):
        if state["t_pub"] is not None and state["hit"] is None and t > state["t_pub"]:
            px = _rgb(msg)
            if not np.array_equal(px, baseline["px"]):
                state["hit"] = (t, int((px != baseline["px"]).sum()))

    p.on_image = on_image
    cpu = CpuMeter(b.node.proc.pid)
    for k in range(trials + 1):  # trial 0 only takes the baseline
        # the reset restarts from the initial scene with the gripper at `hover` (no in-flight
        # message from the last trial can push the rope again)
        resp = p.reset(ply_path=scene_dir, initial_joint_state=p.joint_msg(hover))
        if not resp.success:
            raise RuntimeError(f"reset failed: {resp.message}")
        # hover until an image equal to the rest image arrives (two in a row after the reset)
        n0 = p.count.get(("image", "cam_front"), 0)
        if k == 0:
            p.hold(hover, lambda: p.count.get(("image", "cam_front"), 0) >= n0 + 3, 60)
            baseline["px"] = _rgb(p.last("image", "cam_front")).copy()
            continue
        t_w = time.monotonic()
        same = {"n": 0, "seen": p.count.get(("image", "cam_front"), 0)}

        def settled():
            c = p.count.get(("image", "cam_front"), 0)
            if c > same["seen"]:
                same["seen"] = c
                same["n"] = same["n"] + 1 if np.array_equal(_rgb(p.last("image", "cam_front")), baseline["px"]) else 0
            return same["n"] >= 2

        if not p.hold(hover, settled, 60):
            raise RuntimeError("the rest image did not come back after a reset")
        waits.append(time.monotonic() - t_w)
        p.hold(hover, lambda: False, 0.05 + 0.1 * np.random.default_rng(k).random())  # random phase vs the timers
        state["hit"] = None
        state["t_pub"] = time.monotonic()
        p.publish(in_rope)
        p.hold(in_rope, lambda: state["hit"] is not None, 10)
        if state["hit"] is None:
            say(f"  trial {k}: no image changed within 10 s")
            state["t_pub"] = None
            continue
        lat.append((state["hit"][0] - state["t_pub"]) * 1e3)
        changed_px.append(state["hit"][1])
        state["t_pub"] = None
        say(f"  trial {k}: {lat[-1]:.0f} ms ({changed_px[-1]} bytes of the image changed)")
    p.on_image = None
    st = p.last_status()
    c = cpu.stop()
    say("  " + _cpu_text(c))
    return {"cpu": c, "latency_ms": lat, "median_ms": _pct(lat, 50), "p90_ms": _pct(lat, 90), "min_ms": min(lat, default=float("nan")),
            "max_ms": max(lat, default=float("nan")), "trials": len(lat), "changed_bytes_median": _pct(changed_px, 50),
            "step_ms": float(st.step_time_ms), "render_ms": float(st.render_time_ms)}


def bench_rates(b: _Bench, sweep: Sequence[np.ndarray], seconds: float, say,
                cameras: Sequence[str] = ("cam_front",), engine: Optional[dict] = None) -> dict:
    """Sustained rates while joint states stream at 100 Hz along `sweep` (cycled); image sets
    are counted by the camera with the fewest images. The node's step is compared with the
    node's start-up calibration (the engine at the node's rates) and, given this process's
    ``engine`` figures for the same cameras, with the same sweep stepped back to back and at
    the node's rate here."""
    p = b.probe
    p.hold(sweep[0], lambda: False, 2.0)  # warm-up
    n_img0 = {c: p.count.get(("image", c), 0) for c in cameras}
    img_first = _rgb(p.last("image", "cam_front")).copy() if p.last("image", "cam_front") is not None else None
    st0, t0 = p.last_status(), time.monotonic()
    k0 = len(p.status)
    cpu = CpuMeter(b.node.proc.pid)
    i = 0
    t_next = t0
    while time.monotonic() < t0 + seconds:
        p.publish(sweep[i % len(sweep)])
        i += 1
        t_next += 0.01
        p.spin_until(lambda: time.monotonic() >= t_next, 0.5)
    t1 = time.monotonic()
    st1 = p.last_status()
    window = [m for _, m in list(p.status)[k0:]]
    # a status without the engine's figures is not this node's (the node sets them at start-up)
    dropped = sum(1 for m in window if not m.engine_step_ms > 0)
    window = [m for m in window if m.engine_step_ms > 0]
    res = {
        "cpu": cpu.stop(),
        "rope_in_view_at_rest": bool(p.last("image", "cam_front") is not None and img_first is not None
                                     and np.array_equal(_rgb(p.last("image", "cam_front")), img_first)),
        "seconds": t1 - t0,
        "steps_per_s": (int(st1.step) - int(st0.step)) / (t1 - t0) if st1.step >= st0.step else float("nan"),
        "cameras": list(cameras),
        "images_per_s": min(p.count.get(("image", c), 0) - n_img0[c] for c in cameras) / (t1 - t0),
        "status_step_rate_median": _pct([m.step_rate_hz for m in window], 50),
        "status_step_rate_min": min((m.step_rate_hz for m in window), default=float("nan")),
        "status_image_rate_median": _pct([m.image_rate_hz for m in window], 50),
        "status_image_rate_min": min((m.image_rate_hz for m in window), default=float("nan")),
        "step_ms_median": _pct([m.step_time_ms for m in window], 50),
        "step_ms_p90": _pct([m.step_time_ms for m in window], 90),
        "render_ms_median": _pct([m.render_time_ms for m in window], 50),
        "step_cpu_ms_median": _pct([m.step_cpu_ms for m in window], 50),
        "render_cpu_ms_median": _pct([m.render_cpu_ms for m in window], 50),
        "engine_step_ms": float(window[-1].engine_step_ms) if window else float("nan"),
        "engine_render_ms": float(window[-1].engine_render_ms) if window else float("nan"),
        "lag_ms_median": _pct([m.joint_state_lag_ms for m in window], 50),
        "joint_states_sent": i,
    }
    res["status_without_engine_figures"] = dropped
    res["step_vs_engine"] = res["step_ms_median"] / res["engine_step_ms"] if window else float("nan")
    res["render_vs_engine"] = res["render_ms_median"] / res["engine_render_ms"] if window else float("nan")
    if engine:
        res["bench_step_wall_ms"] = engine["step_wall_ms"]
        res["bench_step_paced_wall_ms"] = engine["step_paced_wall_ms"]
        res["step_vs_bench"] = res["step_ms_median"] / engine["step_wall_ms"]
        res["step_vs_bench_paced"] = res["step_ms_median"] / engine["step_paced_wall_ms"]
    say(f"  {len(cameras)} camera(s): {res['steps_per_s']:.1f} steps/s, {res['images_per_s']:.1f} image sets/s received "
        f"(status medians {res['status_step_rate_median']:.1f} / {res['status_image_rate_median']:.1f} Hz); "
        f"step {res['step_ms_median']:.1f} ms in the node ({res['step_cpu_ms_median']:.1f} CPU) vs "
        f"{res['engine_step_ms']:.1f} alone ({res['step_vs_engine']:.2f}x), render {res['render_ms_median']:.1f} ms "
        f"({res['render_cpu_ms_median']:.1f} CPU) vs {res['engine_render_ms']:.1f} alone "
        f"({res['render_vs_engine']:.2f}x); " + _cpu_text(res["cpu"]) + "; " + load_line())
    if engine:
        say(f"  the same sweep stepped in this process: {engine['step_wall_ms']:.1f} ms back to back "
            f"({res['step_vs_bench']:.2f}x), {engine['step_paced_wall_ms']:.1f} ms at {engine['rate_hz']:g} Hz "
            f"({res['step_vs_bench_paced']:.2f}x)")
    return res


def bench_long(b: _Bench, scene_dir: str, cycle: Sequence[np.ndarray], x0: np.ndarray, steps: int, say) -> dict:
    """A `steps` live run (images off) with the gripper cycling through grasp-and-lift, from a reset."""
    p = b.probe
    ext0 = extent(x0)
    t_reset = p.now_ns()
    resp = p.reset(ply_path=scene_dir, initial_joint_state=p.joint_msg(cycle[0]))
    if not resp.success:
        raise RuntimeError(f"reset failed: {resp.message}")

    def after_reset() -> bool:
        st = p.last_status()
        return st is not None and st.header.stamp.sec * 10**9 + st.header.stamp.nanosec > t_reset
    p.spin_until(after_reset, 10)
    cpu = CpuMeter(b.node.proc.pid)
    t0 = time.monotonic()
    i = 0
    seen = {"max_disp": 0.0, "max_extent": ext0, "clouds": 0, "finite": True}
    last_cloud = {"n": 0}
    prev_step = {"v": 0, "went_back": 0, "total": 0}  # total: steps over restarts (status.step restarts at 0)
    t_next = t0
    last_say = t0
    while True:
        st = p.last_status()
        if st is not None:
            if int(st.step) < prev_step["v"]:
                prev_step["went_back"] += 1
                prev_step["total"] += int(st.step)
            else:
                prev_step["total"] += int(st.step) - prev_step["v"]
            prev_step["v"] = int(st.step)
            if prev_step["total"] >= steps:
                break
        if not b.node.alive():
            raise RuntimeError(f"the node died:\n{b.node.output()[-3000:]}")
        p.publish(cycle[i % len(cycle)])
        i += 1
        t_next += 1.0 / 60.0
        p.spin_until(lambda: time.monotonic() >= t_next, 0.5)
        c = p.count.get(("splats",), 0)
        if c > last_cloud["n"]:
            last_cloud["n"] = c
            x = cloud_means(p.last("splats"))
            fin = bool(np.isfinite(x).all())
            seen["finite"] &= fin
            seen["clouds"] += 1
            if fin:
                seen["max_disp"] = max(seen["max_disp"], float(np.linalg.norm(x - x0, axis=1).max()))
                seen["max_extent"] = max(seen["max_extent"], extent(x))
        if time.monotonic() - last_say > 30:
            last_say = time.monotonic()
            say(f"  step {prev_step['total']} ({prev_step['total'] / (last_say - t0):.0f} steps/s), "
                f"{int(p.last_status().failure_restarts)} failure restarts")
    t1 = time.monotonic()
    # the cloud after the last step
    n0 = p.count.get(("splats",), 0)
    p.hold(cycle[0], lambda: p.count.get(("splats",), 0) > n0, 30)
    x = cloud_means(p.last("splats"))
    fin = bool(np.isfinite(x).all())
    out = b.node.output()
    res = {
        "cpu": cpu.stop(),
        "steps": prev_step["total"], "seconds": t1 - t0, "steps_per_s": prev_step["total"] / (t1 - t0),
        "failure_restarts": int(p.last_status().failure_restarts),
        "settles_since_last_restart": int(getattr(p.last_status(), "settles", 0)),
        "finite_all_clouds": seen["finite"] and fin, "clouds_checked": seen["clouds"] + 1,
        "final_max_disp_m": float(np.linalg.norm(x - x0, axis=1).max()) if fin else float("nan"),
        "max_disp_m": max(seen["max_disp"], float(np.linalg.norm(x - x0, axis=1).max()) if fin else 0.0),
        "extent0_m": ext0, "final_extent_m": extent(x) if fin else float("nan"), "max_extent_m": max(seen["max_extent"], extent(x) if fin else 0.0),
        "step_counter_went_back": prev_step["went_back"], "step_failures_logged": out.count("step failed"),
    }
    say(f"  {res['steps']} steps in {res['seconds']:.0f} s; finite {res['finite_all_clouds']}; max displacement "
        f"{res['max_disp_m']:.3f} m; extent {ext0:.3f} -> max {res['max_extent_m']:.3f} m; "
        f"{res['failure_restarts']} failure restarts (diverged steps caught by the node); "
        f"{res['settles_since_last_restart']} settles since the last restart")
    return res


def node_engine_kwargs(params: Sequence[str] = ()) -> dict:
    """``load_live`` keyword arguments for the engine as the node configures it: the node's
    defaults (``config/nodes/sim_node.yaml``, which a test keeps equal to the node's declared
    defaults) with the ``NAME:=VALUE`` overrides of ``params`` applied, so that the engine
    section times the node's step (settling and the passive-object rule included)."""
    import yaml

    from soma_ros.paths import config_dir

    from soma_ros.live import live_kwargs

    values = yaml.safe_load((config_dir() / "nodes" / "sim_node.yaml").read_text())["/**"]["ros__parameters"]
    for q in params:
        name, _, value = q.partition(":=")
        values[name] = yaml.safe_load(value)
    return live_kwargs(values)


def bench_engine(live, hover, sweep, say, steps: int = 90, renders: int = 10, clouds: int = 10,
                 rate_hz: float = 30.0) -> dict:
    """The node's work without ROS, in this process (1 torch thread): CPU seconds per step
    (gripper moving, out of reach), per render, per splat cloud (to_splats + layout), and the
    cores the node needs at rate_hz / render_rate_hz / splat_rate_hz. CPU time (not wall) is
    counted so the figure holds on a shared machine. The steps are timed twice: back to back,
    and one every ``1/rate_hz`` seconds as the node runs them (median wall and thread CPU time
    of the step): the idle gap between two steps alone makes a step dearer."""
    from soma_ros.core.cloud_layout import splats_to_records
    from soma_ros.live import paced

    def cpu_per(fn, n):
        fn(0)
        c0, w0 = time.process_time(), time.perf_counter()
        for i in range(n):
            fn(i)
        return (time.process_time() - c0) / n * 1e3, (time.perf_counter() - w0) / n * 1e3

    live.reset(live.bundle.splats)
    step_cpu, step_wall = cpu_per(lambda i: live.step(sweep[i % len(sweep)]), steps)
    paced_wall, paced_cpu = [], []
    for i in paced(1.0 / rate_hz, steps):
        _, ms = live.step(sweep[i % len(sweep)])
        paced_wall.append(ms)
        paced_cpu.append(live.last_step_cpu_ms)
    st, tpl, _ = live.snapshot()
    render_cpu, render_wall = cpu_per(lambda i: live.render(st, tpl, hover), renders)
    cloud_cpu, cloud_wall = cpu_per(lambda i: splats_to_records(live.current_splats()), clouds)
    res = {"step_cpu_ms": step_cpu, "step_wall_ms": step_wall, "rate_hz": rate_hz,
           "step_paced_wall_ms": _pct(paced_wall[1:], 50), "step_paced_cpu_ms": _pct(paced_cpu[1:], 50),
           "render_cpu_ms": render_cpu,
           "render_wall_ms": render_wall, "cloud_cpu_ms": cloud_cpu, "cloud_wall_ms": cloud_wall}
    say(f"  step {step_cpu:.1f} ms CPU ({step_wall:.1f} wall) back to back, {res['step_paced_cpu_ms']:.1f} ms CPU "
        f"({res['step_paced_wall_ms']:.1f} wall) at {rate_hz:g} Hz, render {render_cpu:.1f} ms CPU ({render_wall:.1f} wall), "
        f"splat cloud {cloud_cpu:.1f} ms CPU ({cloud_wall:.1f} wall)")
    return res


def bench_flood(b: _Bench, hover, seconds: float, hz: float, say) -> dict:
    p = b.probe
    pid = b.node.proc.pid
    p.publish(names=["x"], positions=[1.0, 2.0])  # warm the reject path
    p.hold(hover, lambda: False, 3.0)
    st0 = p.last_status()
    k0 = len(p.status)
    rss0 = rss_mb(pid)
    names = list(p.names) + list(p.extra)
    good = list(hover) + [hover[p.names.index("panda_finger_joint1")]] * len(p.extra)
    bad = list(good)
    bad[3] = math.nan
    n_img0 = p.count.get(("image", "cam_front"), 0)
    cpu = CpuMeter(pid)
    t0 = time.monotonic()
    sent, rss_samples, next_rss = 0, [rss0], t0 + 1.0
    while (now := time.monotonic()) < t0 + seconds:
        due = int((now - t0) * hz) + 1
        while sent < due:
            p.publish(names=names, positions=bad if sent % 10 == 9 else good)
            sent += 1
        p.executor.spin_once(timeout_sec=0)
        if now >= next_rss:
            rss_samples.append(rss_mb(pid))
            next_rss += 1.0
    t1 = time.monotonic()
    c = cpu.stop()
    imgs = p.count.get(("image", "cam_front"), 0) - n_img0
    st_end = p.last_status()
    window = [m for _, m in list(p.status)[k0:]]
    # a status without the engine's figures is not this node's (the node sets them at start-up)
    dropped = sum(1 for m in window if not m.engine_step_ms > 0)
    window = [m for m in window if m.engine_step_ms > 0]
    p.hold(hover, lambda: False, 3.0)
    st1 = p.last_status()
    rss1 = rss_mb(pid)
    lines = [ln for ln in b.node.output().splitlines() if "rejected /joint_states" in ln]
    res = {
        "cpu": c, "seconds": t1 - t0, "sent": sent, "sent_hz": sent / (t1 - t0),
        "received": int(st1.joint_states_received) - int(st0.joint_states_received),
        "rejected": int(st1.joint_states_rejected) - int(st0.joint_states_rejected),
        "steps_per_s": (int(st_end.step) - int(st0.step)) / (t1 - t0),
        "images_per_s": imgs / (t1 - t0),
        "status_step_rate_median": _pct([m.step_rate_hz for m in window], 50),
        "rss_before_mb": rss0, "rss_peak_mb": max(rss_samples + [rss1]), "rss_after_mb": rss1,
        "rss_first_half_mb": max(rss_samples[: len(rss_samples) // 2 + 1]),
        "rss_second_half_mb": max(rss_samples[len(rss_samples) // 2:]),
        "warn_lines": len(lines), "alive": b.node.alive(),
    }
    say(f"  sent {sent} ({res['sent_hz']:.0f} Hz), received {res['received']}, rejected {res['rejected']}; "
        f"{res['steps_per_s']:.1f} steps/s; RSS {rss0:.0f} -> peak {res['rss_peak_mb']:.0f} -> {rss1:.0f} MB; "
        f"{len(lines)} warning lines; alive {res['alive']}; " + _cpu_text(c))
    return res


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description="soma_sim_node end-to-end benchmark (see module docstring)")
    ap.add_argument("--splats", type=int, default=13000)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--cameras", type=int, nargs="+", default=[1, 3],
                    help="camera counts for the engine and rates sections (1 to 3 fixed cameras)")
    ap.add_argument("--model", default="cpu")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--torch-threads", type=int, default=1)
    ap.add_argument("--rate-hz", type=float, default=30.0)
    ap.add_argument("--render-rate-hz", type=float, default=10.0)
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--sustain-s", type=float, default=20.0)
    ap.add_argument("--long-steps", type=int, default=10000)
    ap.add_argument("--long-splats", type=int, default=None, help="splats for the long run (default --splats)")
    ap.add_argument("--long-run", default="", help="run the long section on this trained RUN (checkpoint.pt + scene/)")
    ap.add_argument("--long-param", action="append", default=[], metavar="NAME:=VALUE",
                    help="an extra soma_sim_node parameter for the long run (repeatable), e.g. passive_exempt_grasped:=false")
    ap.add_argument("--param", action="append", default=[], metavar="NAME:=VALUE",
                    help="an extra soma_sim_node parameter for the latency, rates and flood sections "
                         "(repeatable), e.g. render_process:=true")
    ap.add_argument("--flood-s", type=float, default=30.0)
    ap.add_argument("--flood-hz", type=float, default=1000.0)
    ap.add_argument("--only", nargs="+", default=["engine", "latency", "rates", "long", "flood"],
                    choices=["engine", "latency", "rates", "long", "flood"])
    ap.add_argument("--json", default="", help="also write the results here")
    ap.add_argument("--workdir", default="", help="where the untrained runs go (default: a temporary folder)")
    args = ap.parse_args(argv)
    for flag, given in (("--long-param", args.long_param), ("--param", args.param)):
        bad = [q for q in given if ":=" not in q]
        if bad:
            ap.error(f"{flag} {bad[0]!r}: expected NAME:=VALUE")
    torch.set_num_threads(1)

    from soma_ros.core.scenes import write_untrained_run
    from soma_ros.live import load_live

    def say(msg: str) -> None:
        print(msg, flush=True)

    work = Path(args.workdir or tempfile.mkdtemp(prefix="soma_bench_live_"))
    machine = machine_line(args.torch_threads)
    say(f"machine: {machine}")
    say(load_line() + " (before)")
    results: dict = {"machine": machine, "args": vars(args), "load_before": load_line()}
    t_bench = time.monotonic()

    def prepare(n: int, run=None, cameras=("cam_front",)):
        if run is None:
            run = write_untrained_run(work / f"run_{n}_{args.width}x{args.height}", n=n, model=args.model,
                                      width=args.width, height=args.height)
        live = load_live(str(run[0]), str(run[1]), camera_names=list(cameras) or None)
        g = np.asarray(live.bundle.gravity, dtype=np.float64)
        poser = Poser(live.robot, live.base_to_sim.matrix(), live.required_joints, g)
        x0 = live.snapshot()[0].means.double().numpy()
        grasp, closing = object_grasp(x0, poser.down)
        up = -poser.down
        top = float((x0 @ up).max() - grasp @ up)
        radius = (live.sim.effects.robot_reach() or 0.05)
        # just out of reach: raise until every control point is beyond the robot effect's radius (+5 mm)
        h = top + 0.03
        while True:
            hover = poser.solve(grasp + h * up, closing=closing)
            d = float(torch.cdist(torch.as_tensor(x0), live.action(hover).control_points.double()).min())
            if d > radius + 0.005:
                break
            h += 0.005
        in_rope = poser.solve(grasp, q0=hover, closing=closing)
        return run, live, poser, x0, grasp, closing, hover, in_rope

    base = ["device:=" + args.device, f"torch_threads:={args.torch_threads}", f"rate_hz:={args.rate_hz}",
            f"render_rate_hz:={args.render_rate_hz}"] + args.param + ["cameras:=[cam_front]"]
    if args.param:
        say(f"node parameters: {' '.join(args.param)}")

    if {"engine", "latency", "rates", "flood"} & set(args.only):
        t = time.monotonic()
        run, live, poser, x0, grasp, closing, hover, in_rope = prepare(args.splats)
        say(f"scene: {len(x0)} splats, cam_front {args.width}x{args.height}, {args.model} model (untrained), "
            f"prepared in {time.monotonic() - t:.1f} s")
        names = live.required_joints
        # back and forth along the rope, at the hover height + 1 cm: moving, never touching
        along = np.cross(closing, poser.down)
        tcp_hover = live.action(hover).control_points.double().mean(0).numpy()
        sweep_a = poser.line(tcp_hover - 0.08 * along - 0.01 * poser.down, tcp_hover + 0.08 * along - 0.01 * poser.down,
                             60, q0=hover, closing=closing)
        radius = (live.sim.effects.robot_reach() or 0.05)
        reach = min(float(torch.cdist(torch.as_tensor(x0), live.action(v).control_points.double()).min()) for v in sweep_a)
        if reach <= radius:
            raise RuntimeError(f"the rate sweep comes within {reach:.3f} m of the object (reach {radius} m)")
        sweep = sweep_a + sweep_a[::-1]
        for n_cams in args.cameras if {"engine", "rates"} & set(args.only) else []:
            scene_n, cam_names = with_cameras(Path(run[1]), n_cams, work / f"scene_{n_cams}cam")
            run_n = (run[0], scene_n)
            if "engine" in args.only:
                say(f"engine, {n_cams} camera(s) {', '.join(cam_names)}: the node's work without ROS, in this process")
                live_n = load_live(str(run_n[0]), str(run_n[1]), camera_names=cam_names, **node_engine_kwargs(args.param))
                e = bench_engine(live_n, hover, sweep, say, rate_hz=args.rate_hz)
                e["cores_needed"] = (args.rate_hz * e["step_cpu_ms"] + args.render_rate_hz * e["render_cpu_ms"]
                                     + 5.0 * e["cloud_cpu_ms"]) / 1e3
                e["cameras"] = cam_names
                results.setdefault("engine", {})[str(n_cams)] = e
                say(f"  cores needed at {args.rate_hz:.0f} Hz steps, {args.render_rate_hz:.0f} Hz image sets, 5 Hz "
                    f"clouds: {e['cores_needed']:.2f} (plus ROS overhead); {load_line()}")
                del live_n
            if "rates" in args.only:
                say(f"rates, {n_cams} camera(s): {args.sustain_s:.0f} s, joint states at 100 Hz sweeping along the "
                    f"rope just out of reach")
                params = base[:-1] + [f"cameras:=[{','.join(cam_names)}]"]
                b = _Bench(run_n, params, names, cam_names, splats=False)
                try:
                    b.started(hover, ("image", cam_names[-1]))
                    b.probe.reset(ply_path=str(run_n[1]), initial_joint_state=b.probe.joint_msg(sweep[0]))
                    results.setdefault("rates", {})[str(n_cams)] = bench_rates(
                        b, sweep, args.sustain_s, say, cam_names, engine=results.get("engine", {}).get(str(n_cams)))
                finally:
                    b.close()
        if {"latency", "flood"} & set(args.only):
            b = _Bench(run, base, names, ["cam_front"], splats=False)
            try:
                b.started(hover, ("image", "cam_front"))
                if "latency" in args.only:
                    say(f"latency: {args.trials} trials (gripper from just out of reach into the rope by one message)")
                    results["latency"] = bench_latency(b, str(run[1]), hover, in_rope, args.trials, say)
                if "flood" in args.only:
                    say(f"flood: {args.flood_hz:.0f} Hz for {args.flood_s:.0f} s (1 in 10 with a NaN)")
                    b.probe.reset(ply_path=str(run[1]), initial_joint_state=b.probe.joint_msg(hover))
                    results["flood"] = bench_flood(b, hover, args.flood_s, args.flood_hz, say)
            finally:
                b.close()

    if "long" in args.only:
        n = args.long_splats or args.splats
        given = None
        if args.long_run:
            given = (Path(args.long_run) / "checkpoint.pt", Path(args.long_run) / "scene")
        run, live, poser, x0, grasp, closing, hover, in_rope = prepare(n, run=given, cameras=() if given else ("cam_front",))
        cycle = grasp_trajectory(poser, grasp, lift=0.10, above=0.10, steps=30, closing=closing)
        cycle = cycle + cycle[::-1]
        what = f"the trained run {args.long_run}" if given else "the untrained model"
        say(f"long: {args.long_steps} steps, {len(x0)} splats, {what}, rate_hz 1000 (as fast as it goes), images off, "
            f"gripper cycling grasp-lift-lower ({len(cycle)} poses at 60 Hz)")
        params = ["device:=" + args.device, f"torch_threads:={args.torch_threads}", "rate_hz:=1000.0",
                  "render_rate_hz:=0.0", "splat_rate_hz:=0.5"] + ([] if given else ["cameras:=[cam_front]"])
        params += args.long_param
        if args.long_param:
            say(f"long: node parameters {' '.join(args.long_param)}")
        b = _Bench(run, params, live.required_joints, [], splats=True)
        try:
            b.started(cycle[0], ("splats",))
            results["long"] = bench_long(b, str(run[1]), cycle, x0, args.long_steps, say)
            results["long"]["model"] = what
            results["long"]["splats"] = len(x0)
        finally:
            b.close()

    results["load_after"] = load_line()
    results["seconds"] = time.monotonic() - t_bench
    say("")
    say(format_report(results))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float))
    return 0


def format_report(r: dict) -> str:
    a = r["args"]
    lines = [f"soma_sim_node benchmark -- {r['machine']}"]
    if {"latency", "rates", "flood"} & set(r):
        lines.append(f"scene: {a['splats']} splats, {a['model']} model (untrained), cameras {a['width']}x{a['height']}, "
                     f"rate_hz {a['rate_hz']:.0f}, render_rate_hz {a['render_rate_hz']:.0f}, splat_rate_hz 5, "
                     f"device {a['device']}" + (f", {' '.join(a['param'])}" if a.get("param") else ""))
    lines += [f"{r.get('load_before', '')} before, {r.get('load_after', '')} after ({r.get('seconds', 0):.0f} s)", ""]
    row = "{:<44} {:>14} {:>12}"
    lines.append(row.format("measure", "value", "target"))
    for n, E in r.get("engine", {}).items():
        lines.append(row.format(f"engine ({n} camera(s)) step, CPU (wall)", f"{E['step_cpu_ms']:.1f} ({E['step_wall_ms']:.1f}) ms", "<= 33 ms"))
        if "step_paced_cpu_ms" in E:
            lines.append(row.format(f"  step at {E['rate_hz']:g} Hz, CPU (wall)",
                                    f"{E['step_paced_cpu_ms']:.1f} ({E['step_paced_wall_ms']:.1f}) ms", ""))
        lines.append(row.format("  render of all cameras, CPU (wall)", f"{E['render_cpu_ms']:.0f} ({E['render_wall_ms']:.0f}) ms", ""))
        lines.append(row.format("  splat cloud, CPU (wall)", f"{E['cloud_cpu_ms']:.1f} ({E['cloud_wall_ms']:.1f}) ms", ""))
        lines.append(row.format("  cores the node needs at the target rates", f"{E['cores_needed']:.2f}", "+ ROS"))
    if "latency" in r:
        L = r["latency"]
        lines.append(row.format(f"joint state -> changed image, median ({L['trials']} trials)", f"{L['median_ms']:.0f} ms", ""))
        lines.append(row.format("  p90 / min / max", f"{L['p90_ms']:.0f}/{L['min_ms']:.0f}/{L['max_ms']:.0f} ms", ""))
        lines.append(row.format("  node step / render time (last status)", f"{L['step_ms']:.1f}/{L['render_ms']:.0f} ms", ""))
    for n, R in r.get("rates", {}).items():
        lines.append(row.format(f"{n} camera(s): sustained step rate (status.step/s)", f"{R['steps_per_s']:.1f} Hz",
                                f">= 29 Hz ({R['steps_per_s'] / 30:.2f}x of 30)"))
        lines.append(row.format("  status step_rate_hz median / min", f"{R['status_step_rate_median']:.1f}/{R['status_step_rate_min']:.1f}", ""))
        lines.append(row.format("  sustained image-set rate (received / s)", f"{R['images_per_s']:.1f} Hz", ">= 10 Hz"))
        lines.append(row.format("  status image_rate_hz median / min", f"{R['status_image_rate_median']:.1f}/{R['status_image_rate_min']:.1f}", ""))
        lines.append(row.format("  step in the node median / p90 (CPU)", f"{R['step_ms_median']:.1f}/{R['step_ms_p90']:.1f} ({R['step_cpu_ms_median']:.1f}) ms", "<= 33 ms"))
        lines.append(row.format(f"  step alone at {a['rate_hz']:g} Hz (node start-up)", f"{R['engine_step_ms']:.1f} ms",
                                f"node {R['step_vs_engine']:.2f}x (<= 1.3x)"))
        if "step_vs_bench" in R:
            lines.append(row.format("  step alone, this process, back to back", f"{R['bench_step_wall_ms']:.1f} ms",
                                    f"node {R['step_vs_bench']:.2f}x"))
            lines.append(row.format(f"  step alone, this process, at {a['rate_hz']:g} Hz",
                                    f"{R['bench_step_paced_wall_ms']:.1f} ms", f"node {R['step_vs_bench_paced']:.2f}x"))
        lines.append(row.format("  render in the node median (CPU)", f"{R['render_ms_median']:.0f} ({R['render_cpu_ms_median']:.0f}) ms", ""))
        lines.append(row.format(f"  render alone at {a['render_rate_hz']:g} Hz (node start-up)", f"{R['engine_render_ms']:.0f} ms",
                                f"node {R['render_vs_engine']:.2f}x"))
        lines.append(row.format("  rope at rest in view throughout (same image)", str(R.get("rope_in_view_at_rest")), "True"))
        lines.append(row.format("  cores used: node / probe / others", "{:.2f}/{:.2f}/{:.2f}".format(
            R["cpu"]["node_cores"], R["cpu"]["probe_cores"], R["cpu"]["others_cores"]), f"of {R['cpu']['cores']}"))
    if "long" in r:
        G = r["long"]
        lines.append(row.format(f"long run ({G.get('splats', '?')} splats): steps at {G['steps_per_s']:.0f}/s", f"{G['steps']}", f">= {a['long_steps']}"))
        lines.append(row.format("  model", str(G.get("model", ""))[-40:], ""))
        lines.append(row.format("  all clouds finite / failure restarts", f"{G['finite_all_clouds']}/{G.get('failure_restarts', '?')}", "True/0"))
        lines.append(row.format("  max displacement from the initial scene", f"{G['max_disp_m']:.3f} m", ""))
        lines.append(row.format("  extent initial -> max", f"{G['extent0_m']:.3f}->{G['max_extent_m']:.3f} m",
                                f"ratio {G['max_extent_m'] / G['extent0_m']:.2f}"))
    if "flood" in r:
        F = r["flood"]
        lines.append(row.format(f"flood {F['sent_hz']:.0f} Hz x {F['seconds']:.0f} s: received / sent", f"{F['received']}/{F['sent']}",
                                f"{F['received'] / max(F['sent'], 1):.2f}"))
        lines.append(row.format("  rejected (1 in 10 sent had a NaN)", f"{F['rejected']}", f"{F['rejected'] / max(F['received'], 1):.2f} of rcvd"))
        lines.append(row.format("  steps/s, images/s during the flood", f"{F['steps_per_s']:.1f}/{F['images_per_s']:.1f} Hz", ""))
        lines.append(row.format("  node RSS before / peak / after", f"{F['rss_before_mb']:.0f}/{F['rss_peak_mb']:.0f}/{F['rss_after_mb']:.0f} MB",
                                f"+{F['rss_after_mb'] - F['rss_before_mb']:.0f} MB"))
        lines.append(row.format("  RSS max 1st half / 2nd half", f"{F['rss_first_half_mb']:.0f}/{F['rss_second_half_mb']:.0f} MB", ""))
        lines.append(row.format("  warning lines logged (throttle 2 s) / alive", f"{F['warn_lines']}/{F['alive']}", ""))
        lines.append(row.format("  cores used: node / probe / others", "{:.2f}/{:.2f}/{:.2f}".format(
            F["cpu"]["node_cores"], F["cpu"]["probe_cores"], F["cpu"]["others_cores"]), f"of {F['cpu']['cores']}"))
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
