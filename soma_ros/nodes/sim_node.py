"""soma_sim_node: the live simulator node (the digital twin on ROS 2).

Follows /joint_states, steps the learned simulator at a fixed rate from the
latest action, and publishes what the cameras would see.

Topics (``<p>`` = the `topic_prefix` parameter, default /soma):

  sub  /joint_states             sensor_msgs/JointState  sensor-data QoS (reliable publishers work too)
  pub  <p>/<cam>/image_raw       sensor_msgs/Image rgb8
  pub  <p>/<cam>/depth           sensor_msgs/Image 32FC1, metres (NaN = no splat, REP 118)
  pub  <p>/<cam>/camera_info     sensor_msgs/CameraInfo (of the image and of the aligned depth)
  pub  <p>/splats                sensor_msgs/PointCloud2, soma_msgs/SplatLayout with packed rgb
  pub  <p>/status                soma_msgs/SimStatus
  pub  /tf, /tf_static           one tree: world -> sim frame, cameras, robot links (:mod:`.robot_tf`)
  pub  /robot_description        std_msgs/String, transient local (with publish_robot_tf)
  srv  <p>/reset                 soma_msgs/srv/ResetScene

Start: ``soma_sim_node --ros-args -p checkpoint:=RUN/checkpoint.pt -p scene:=RUN/scene``
(or ``--params-file config/nodes/sim_node.yaml`` plus those two ``-p``).

Threads: physics steps, renders and splat clouds each run in their own
fixed-rate thread (:mod:`.loops`), so a slow render never delays a step; the
main thread takes /joint_states straight from the subscription (:meth:`SomaSimNode.serve`),
at most ``input_rate_hz`` messages a second (under a flood the middleware keeps
the newest and the rest are counted as dropped), so input is never queued behind
a step and cannot starve it. The
reset service has its own node (``<name>_reset``) and executor thread, and each
reset runs in a worker thread with a time limit (``reset_timeout_s``): reading,
checking and binding a scene never stops /joint_states from being taken, and a
second reset while one runs is answered "busy".

Reset input is untrusted (anyone on the DDS domain can call it; see
the security section of docs/ros_interface.md): files are read only inside ``scene_dirs``
(:class:`~soma_ros.core.scene_guard.ScenePathPolicy`), sizes are checked from
the header or the message before anything is allocated, and the scene must be
physically plausible beside the starting one (:class:`SceneLimits`). Every published image, depth map, cloud and camera TF
comes from one consistent frame (the state of one step, the joint state that
step used and that step's stamp). Publishers keep the last message only, so a
slow subscriber never stalls the node.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections import deque
from typing import NamedTuple, Optional

import numpy as np
import rclpy
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, JointState, PointCloud2
from soma_msgs.msg import SimStatus
from soma_msgs.srv import ResetScene

from ..core.cloud_layout import REQUIRED_FIELDS, SPLAT_FIELDS
from ..core.scene_guard import (
    SceneExtent,
    SceneLimits,
    ScenePathPolicy,
    SceneRefused,
    check_cloud_layout,
    check_physical,
    read_scene_file,
)
from ..core.splats import Splats
from .conversions import (
    camera_info,
    cloud_to_splats_msg,
    image_depth32,
    image_rgb8,
    ns_from_stamp,
    splats_to_cloud,
    stamp_from_ns,
)
from .loops import FixedRateLoop, StepPhase
from .robot_tf import RobotTf, camera_frame_id
from .qos import JOINT_STATES_QOS, SENSOR_OUT_QOS, STATUS_QOS


class Frame(NamedTuple):
    """What one step left behind, published as a unit by the output threads."""

    state: object  # SimState
    template: Splats
    joint_vec: Optional[np.ndarray]  # the joint state this step used (None: no robot yet)
    stamp_ns: int  # node clock at the step
    step: int


class RateMeter:
    def __init__(self, window_s: float = 1.0) -> None:
        self.window = window_s
        self.t: deque[float] = deque()

    def tick(self) -> None:
        now = time.monotonic()
        self.t.append(now)
        while self.t and now - self.t[0] > self.window:
            self.t.popleft()

    def rate(self) -> float:
        if len(self.t) < 2:
            return 0.0
        span = self.t[-1] - self.t[0]
        return (len(self.t) - 1) / span if span > 0 else 0.0


def _renderer_name() -> str:
    from ..core import raster_kernel

    return "compiled CPU kernels" if raster_kernel.available() else "pure-torch reference"


def _one_line(exc: BaseException) -> str:
    """An exception as one line of at most 300 characters (its type when it has no message)."""
    text = " ".join(str(exc).split())
    if not isinstance(exc, ValueError):
        text = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return text[:300] or type(exc).__name__


def _parameter_error(exc: ParameterException) -> str:
    """rclpy's refusal of a ``--ros-args -p`` value as one line that starts with the parameter's
    name (rclpy words it "<reason>: <name>")."""
    text = " ".join(str(exc).split())
    reason, sep, name = text.rpartition(": ")
    if "of type 'INTEGER', expecting type 'DOUBLE'" in reason:
        reason += " (write a double with a decimal point, e.g. 30.0)"
    return (f"parameter '{name}': {reason}" if sep and name and " " not in name else text)[:300]


def _float_param(node: Node, name: str, default: float, desc: str, lo: float, hi: float, read_only: bool = False) -> float:
    node.declare_parameter(name, default, ParameterDescriptor(
        description=desc, read_only=read_only,
        floating_point_range=[FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]))
    return float(node.get_parameter(name).value)


class SomaSimNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("soma_sim_node", **kwargs)
        p = self.declare_parameter
        p("checkpoint", "", ParameterDescriptor(description="trained simulator checkpoint (.pt) from `soma train`"))
        p("scene", "", ParameterDescriptor(description="scene bundle directory (scene.json + splats.ply) from `soma train`/`soma reconstruct`"))
        p("robot_config", "", ParameterDescriptor(description="robot config name or YAML (default: the scene bundle's)"))
        p("cameras", [""], ParameterDescriptor(description="cameras to render (default: all of the scene bundle)"))
        p("device", "cpu", ParameterDescriptor(description="torch device: cpu or cuda[:N]"))
        p("world_frame", "world", ParameterDescriptor(description="parent frame of the simulation frame"))
        p("sim_frame", "soma_sim", ParameterDescriptor(description="frame of the simulated splats (identity to the scene's frame)"))
        p("topic_prefix", "/soma", ParameterDescriptor(description="prefix of published topics and the reset service"))
        p("torch_threads", 1, ParameterDescriptor(description="torch intra-op threads (1 beside other work)"))
        p("render_process", False, ParameterDescriptor(
            description="render the images in a child process (CPU device, soma_ros.live_render) instead of a "
                        "thread of the node", read_only=True))
        p("align_to_steps", True, ParameterDescriptor(
            description="start each render, splat cloud and /tf publish right after a physics step ends, so that "
                        "their Python work does not overlap the step's (images wait at most one step period)",
            read_only=True))
        p("publish_robot_tf", True, ParameterDescriptor(
            description="publish the robot's links on /tf and /robot_description as robot_state_publisher does "
                        "(false when the real robot's robot_state_publisher runs beside the node)"))
        self.rate_hz = _float_param(self, "rate_hz", 30.0, "physics step rate, Hz", 0.5, 1000.0)
        self.render_rate_hz = _float_param(self, "render_rate_hz", 10.0, "image publish rate, Hz (0 = no images)", 0.0, 120.0)
        self.splat_rate_hz = _float_param(self, "splat_rate_hz", 5.0, "splat cloud publish rate, Hz (0 = none)", 0.0, 120.0)
        self.tf_rate_hz = _float_param(self, "tf_rate_hz", 10.0, "robot link /tf publish rate, Hz (0 = none)", 0.0, 1000.0)
        self.render_scale = _float_param(self, "render_scale", 1.0, "image scale relative to the bundle's cameras", 0.05, 4.0)
        _float_param(self, "max_object_travel_m", 2.0,
                     "a step that puts a splat this far outside the initial scene's bounding sphere "
                     "counts as diverged: logged, and the scene restarts (0 = no check), m", 0.0, 1000.0)
        _float_param(self, "settle_time_s", 2.0,
                     "settle after this long with the robot out of reach and the object still "
                     "(slower than settle_speed_mps): the current configuration becomes the new "
                     "initial state, which stops a learned model's slow creep (0 = never), s",
                     0.0, 3600.0)
        _float_param(self, "settle_speed_mps", 0.01,
                     "a splat slower than this counts as still for settling, m/s", 1e-6, 10.0)
        _float_param(self, "passive_friction", 0.5,
                     "passive-object rule: when no force but gravity, the support and direct "
                     "effects acts, the learned dynamics may not speed the object up "
                     "horizontally or upwards, and on the table Coulomb friction with this "
                     "coefficient brakes it (negative = off)", -1.0, 10.0)
        p("passive_exempt_grasped", True, ParameterDescriptor(
            description="passive-object rule: steps where the model's own terms (its robot coupling) act with the "
                        "gripper closed are not passive, as in its training episodes (false: the rule on every step)"))
        self.max_joint_age = _float_param(self, "max_joint_state_age_s", 1.0,
                                          "hold the robot still when the newest joint state is older than this, s",
                                          0.01, 3600.0)
        self.future_tolerance = _float_param(self, "future_stamp_tolerance_s", 0.1,
                                             "joint states stamped further than this ahead of the node clock are "
                                             "rejected (they would make every later message look older), s",
                                             0.0, 3600.0, read_only=True)
        self.joint_limit_margin = _float_param(self, "joint_limit_margin", 0.05,
                                               "joint states with a position further than this outside the URDF "
                                               "limits are rejected (rad or m)", 0.0, 1000.0, read_only=True)
        self.input_rate_hz = _float_param(self, "input_rate_hz", 200.0,
                                          "most /joint_states messages taken per second; under a flood the newest "
                                          "is kept and the others count as dropped, Hz", 1.0, 100000.0, read_only=True)
        p("scene_dirs", [""], ParameterDescriptor(
            read_only=True, description="folders a reset's ply_path may be read from, symlinks resolved (default: the scene "
                        "parameter's folder and ~/.ros/soma_scenes)"))
        p("max_splats", 200000, ParameterDescriptor(read_only=True, description="most splats a reset scene may have (checked from "
                                                                "the file header or the message before reading)"))
        self.max_scene_mb = _float_param(self, "max_scene_file_mb", 256.0, "largest scene file a reset reads, MiB",
                                         0.001, 1e6, read_only=True)
        self.max_scale_ratio = _float_param(self, "max_splat_scale_ratio", 0.05,
                                            "a reset scene's largest splat standard deviation, as a fraction of the "
                                            "starting scene's diameter", 1e-6, 1e6, read_only=True)
        self.max_extent_ratio = _float_param(self, "max_scene_extent_ratio", 10.0,
                                             "a reset scene's largest bounding radius, as a multiple of the starting "
                                             "scene's", 1e-3, 1e6, read_only=True)
        self.max_scene_offset = _float_param(self, "max_scene_offset_m", 2.0,
                                             "how far a reset scene's centre may lie outside the starting scene's "
                                             "bounding sphere, m", 0.0, 1e6, read_only=True)
        self.reset_timeout = _float_param(self, "reset_timeout_s", 10.0,
                                          "a reset not done within this is refused (the running scene is kept), s",
                                          0.1, 3600.0, read_only=True)

        self.switch_interval_ms = _float_param(
            self, "switch_interval_ms", 5.0,
            "Python's thread switch interval (sys.setswitchinterval): how long a thread running Python "
            "keeps the interpreter lock while another waits for it, ms", 0.05, 100.0, read_only=True)

        import torch

        torch.set_num_threads(int(self.get_parameter("torch_threads").value))
        sys.setswitchinterval(self.switch_interval_ms / 1e3)
        gp = lambda n: self.get_parameter(n).value  # noqa: E731
        self.align_to_steps = bool(gp("align_to_steps"))
        prefix = gp("topic_prefix").rstrip("/")
        self.world_frame, self.sim_frame = gp("world_frame"), gp("sim_frame")
        ckpt, scene = gp("checkpoint"), gp("scene")
        if not ckpt or not scene:
            raise ValueError("parameters 'checkpoint' and 'scene' are required "
                             "(soma_sim_node --ros-args -p checkpoint:=RUN/checkpoint.pt -p scene:=RUN/scene)")
        from ..live import LIVE_PARAMETERS, JointStateFilter, joint_limits, live_kwargs, load_live

        cams = [c for c in gp("cameras") if c]
        self.live = load_live(ckpt, scene, camera_names=cams or None, device=gp("device"),
                              **live_kwargs({n: gp(n) for n in LIVE_PARAMETERS}))
        if gp("robot_config"):
            from ..core.robot import RobotModel

            self.live.robot = RobotModel.from_config(gp("robot_config"))
        # A stamp far ahead of the clock, once accepted, would make every later message "go backwards".
        self._joint_limits = joint_limits(self.live.robot, self.live.required_joints)
        self.joints = JointStateFilter(self.live.required_joints, max_future_s=self.future_tolerance,
                                       limits=self._joint_limits, limit_margin=self.joint_limit_margin)
        self.limits = SceneLimits(max_splats=int(gp("max_splats")), max_file_bytes=int(self.max_scene_mb * 2**20),
                                  max_scale_ratio=self.max_scale_ratio, max_extent_ratio=self.max_extent_ratio,
                                  max_offset_m=self.max_scene_offset)
        dirs = [d for d in gp("scene_dirs") if d] or [scene, "~/.ros/soma_scenes"]
        self.scene_policy = ScenePathPolicy(dirs)
        self._start_extent = SceneExtent.of(self.live.template)
        self.get_logger().info(
            f"loaded {ckpt} and scene {scene}: {len(self.live.template)} splats, cameras "
            f"{', '.join(c.name for c in self.live.cameras)}, joints {', '.join(self.live.required_joints)}")
        self.get_logger().info(f"passive-object rule: {self.live.sim.config.dynamics.passive_rule_text()}")
        self.get_logger().info(f"reset reads scene files only inside: {', '.join(map(str, self.scene_policy.dirs))}")
        # the engine's own step and render times at the node's rates (periods capped at 0.1 s, so
        # that start-up stays short at low rates), reported in /soma/status beside the in-node ones
        self.engine = self.live.calibrate(
            step_period_s=min(0.1, 1.0 / self.rate_hz),
            render_period_s=min(0.1, 1.0 / self.render_rate_hz) if self.render_rate_hz > 0 else 0.0)
        self.get_logger().info(
            f"engine alone: step {self.engine.step_ms:.1f} ms, render {self.engine.render_ms:.1f} ms "
            f"({len(self.live.cameras)} camera(s) {self.live.cameras[0].width}x{self.live.cameras[0].height}"
            f"{f' x {self.render_scale:g}' if self.render_scale != 1.0 else ''}, renderer "
            f"{_renderer_name()}, torch threads {torch.get_num_threads()})")

        # the renderer: a child process on CPU (soma_ros.live_render), else a thread of this node
        self._renderer = None
        self._render_template = None
        if self.render_rate_hz > 0 and bool(gp("render_process")) and self.live.state.means.device.type == "cpu":
            from ..live_render import RenderProcess, RenderProcessError

            c0 = self.live.cameras[0]
            rig = self.live.camera_rig(self.live.neutral_joint_vec())
            try:
                self._renderer = RenderProcess(rig.width, rig.height, len(rig), dtype=self.live.state.means.dtype,
                                               torch_threads=int(gp("torch_threads")))
                self._set_render_scene(self.live.template)
                self.get_logger().info(f"rendering in process {self._renderer.pid} ({len(rig)} x "
                                       f"{rig.width}x{rig.height}, {c0.name} first)")
            except (RenderProcessError, OSError) as exc:
                self.get_logger().error(f"render process did not start ({exc}): rendering in the node")
                if self._renderer is not None:
                    self._renderer.close()
                self._renderer = None

        self.pub_splats = self.create_publisher(PointCloud2, f"{prefix}/splats", SENSOR_OUT_QOS)
        self.pub_status = self.create_publisher(SimStatus, f"{prefix}/status", STATUS_QOS)
        self.pub_img, self.pub_depth, self.pub_info = {}, {}, {}
        for c in self.live.cameras:
            self.pub_img[c.name] = self.create_publisher(Image, f"{prefix}/{c.name}/image_raw", SENSOR_OUT_QOS)
            self.pub_depth[c.name] = self.create_publisher(Image, f"{prefix}/{c.name}/depth", SENSOR_OUT_QOS)
            self.pub_info[c.name] = self.create_publisher(CameraInfo, f"{prefix}/{c.name}/camera_info", SENSOR_OUT_QOS)
        self.sub_js = self.create_subscription(JointState, "/joint_states", self._on_joint_state, JOINT_STATES_QOS)
        # the reset service on its own node and executor thread (started in start()): a reset never
        # holds up the executor that takes /joint_states
        self._reset_node = rclpy.create_node(f"{self.get_name()}_reset", namespace=self.get_namespace(),
                                             context=self.context, start_parameter_services=False)
        # reentrant on two threads: a request that arrives while a reset runs is taken and answered "busy"
        self.srv_reset = self._reset_node.create_service(ResetScene, f"{prefix}/reset", self._on_reset,
                                                         callback_group=ReentrantCallbackGroup())
        self._reset_executor = MultiThreadedExecutor(num_threads=2, context=self.context)
        self._reset_executor.add_node(self._reset_node)
        self._reset_thread = threading.Thread(target=self._spin_reset, name="soma_reset_srv", daemon=True)
        self._reset_mutex = threading.Lock()  # guards _reset_busy
        self._reset_busy = False
        self._commit_lock = threading.Lock()  # a reset's commit against its abandonment on timeout
        self._stopping = threading.Event()

        self.robot_tf = RobotTf(self, self.live, self.world_frame, self.sim_frame, bool(gp("publish_robot_tf")))
        self._step_ms = 0.0
        self._step_cpu_ms = 0.0
        self._render_ms = 0.0
        self._render_cpu_ms = 0.0
        self._lag_ms = 0.0
        self._step_rate = RateMeter()
        self._image_rate = RateMeter()
        self._step_lock = threading.Lock()
        self._phase = StepPhase()
        self._failure_resets = 0
        self._set_frame(None)
        self.loops = [FixedRateLoop("soma_step", self.rate_hz, self._on_step)]
        if self.tf_rate_hz > 0:
            self.loops.append(FixedRateLoop("soma_tf", self.tf_rate_hz, self._on_tf))
        if self.render_rate_hz > 0:
            self.loops.append(FixedRateLoop("soma_render", self.render_rate_hz, self._on_render))
        if self.splat_rate_hz > 0:
            self.loops.append(FixedRateLoop("soma_splats", self.splat_rate_hz, self._on_splats))

    def start(self) -> None:
        """Start the physics and output threads and the reset service (after the node is in an executor)."""
        for loop in self.loops:
            loop.start()
        self._reset_thread.start()

    def stop(self, timeout: float = 1.5) -> None:
        """Stop the threads (all of them within ``timeout`` s); nothing is published after this returns.
        A reset still running is abandoned: its thread is a daemon and commits nothing."""
        self._stopping.set()
        deadline = time.monotonic() + timeout
        for loop in self.loops:
            loop.request_stop()
        for loop in self.loops:
            if not loop.stop(timeout=max(0.0, deadline - time.monotonic())):
                self.get_logger().warn(f"thread {loop.name} did not stop within {timeout:g} s")
        if self._reset_thread.is_alive():
            self._reset_thread.join(timeout=max(0.0, deadline - time.monotonic()))
        if self._renderer is not None:
            self._renderer.close(timeout_s=max(0.2, deadline - time.monotonic()))

    def destroy_node(self) -> None:
        self._stopping.set()
        if self._reset_thread.is_alive():
            self._reset_thread.join(timeout=0.5)
        self._reset_executor.shutdown(timeout_sec=0.1)
        self._reset_node.destroy_node()
        super().destroy_node()

    def _spin_reset(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            while not self._stopping.is_set() and self.context.ok():
                self._reset_executor.spin_once(timeout_sec=0.1)
        except (ExternalShutdownException, KeyboardInterrupt):
            pass

    def _set_frame(self, vec: Optional[np.ndarray], stamp_ns: Optional[int] = None) -> None:
        state, template, steps = self.live.snapshot()
        self._frame = Frame(state, template, vec, int(stamp_ns or self.get_clock().now().nanoseconds), steps)

    # ----------------------------------------------------------------- inputs
    def _on_joint_state(self, msg: JointState, info) -> None:
        """O(joints) work: validate and store. ``info``: the message info; its publication sequence
        number counts the messages the middleware dropped for newer ones."""
        from ..live import JointStateRejected

        self.joints.count_sequence(info.get("publication_sequence_number") if isinstance(info, dict) else None)
        now = self.get_clock().now().nanoseconds
        stamp = ns_from_stamp(msg.header.stamp)
        if stamp == 0:
            stamp = now
        try:
            self.joints.push(msg.name, msg.position, stamp, now_ns=now)
        except JointStateRejected as exc:
            self.get_logger().warn(f"rejected /joint_states: {exc} ({self.joints.rejected} rejected so far)",
                                   throttle_duration_sec=2.0)

    def _on_reset(self, req: ResetScene.Request, resp: ResetScene.Response) -> ResetScene.Response:
        """Runs on the reset thread: one worker at a time, answered within ``reset_timeout_s``."""
        with self._reset_mutex:
            busy, self._reset_busy = self._reset_busy, True
        if busy:
            return self._refuse(resp, "busy: another reset is still running")
        job: dict = {}
        ticket = {"abandoned": False, "committed": False}  # guarded by _commit_lock
        done = threading.Event()

        def work() -> None:
            try:
                job["n"] = self._reset_work(req, ticket)
            except BaseException as exc:  # noqa: BLE001 - every failure leaves the old scene running
                # only the message is kept: the exception's traceback holds the request (a refused
                # 128 MB cloud among them) in a reference cycle with `job` until a garbage collection
                job["error"] = _one_line(exc)
            finally:
                done.set()
                with self._reset_mutex:
                    self._reset_busy = False

        t0 = time.monotonic()
        threading.Thread(target=work, name="soma_reset", daemon=True).start()
        while not done.wait(0.05):
            if self._stopping.is_set() or time.monotonic() - t0 > self.reset_timeout:
                with self._commit_lock:
                    ticket["abandoned"] = not ticket["committed"]
                if ticket["abandoned"]:
                    return self._refuse(resp, f"not done within reset_timeout_s ({self.reset_timeout:g} s)")
        if "error" in job:
            return self._refuse(resp, job["error"])
        n = job["n"]
        resp.success, resp.num_splats = True, n
        resp.message = f"scene reset: {n} splats"
        self.get_logger().info(resp.message)
        return resp

    def _refuse(self, resp: ResetScene.Response, why: str) -> ResetScene.Response:
        resp.num_splats = len(self.live.template)
        resp.success = False
        resp.message = f"reset refused: {why}"
        self.get_logger().warn(resp.message)
        return resp

    def _reset_work(self, req: ResetScene.Request, ticket: dict) -> int:
        """Read and check the requested scene, build what it needs, then swap it in (unless abandoned)."""
        cloud = req.splats
        if int(cloud.width) * int(cloud.height) > 0 or len(cloud.data):
            check_cloud_layout(cloud, self.limits, REQUIRED_FIELDS, SPLAT_FIELDS)
            new = cloud_to_splats_msg(cloud)
        elif req.ply_path:
            new = read_scene_file(req.ply_path, self.scene_policy, self.limits)
        else:
            raise SceneRefused("the request has neither splats (0 points) nor a ply_path")
        check_physical(new, self._start_extent, self.limits)
        init = None
        if len(req.initial_joint_state.name):
            from ..live import JointStateFilter

            init = (list(req.initial_joint_state.name), list(req.initial_joint_state.position))
            JointStateFilter(self.live.required_joints, limits=self._joint_limits,
                             limit_margin=self.joint_limit_margin).push(*init, 0)  # validate before anything changes
        prepared = self.live.prepare(new)  # the hierarchy and graphs, built while steps go on
        with self._commit_lock:
            if ticket["abandoned"]:
                raise SceneRefused("abandoned after reset_timeout_s")
            ticket["committed"] = True
            with self._step_lock:  # not between a step's joint sample and its step
                n = self.live.reset(new, prepared)
                if init is not None:
                    self.joints.clear()
                    self.joints.push(*init, self.get_clock().now().nanoseconds)
                self._set_frame(self.joints.sample())
        return n

    def serve(self, executor, stop: threading.Event, others_period_s: float = 1.0) -> None:
        """The main thread's loop until ``stop`` is set or the context ends: wait for /joint_states
        or a request to one of the node's services (its parameter services), take one message at
        a time from the subscription (at most ``input_rate_hz`` a second, so a flood cannot starve
        the steps), and hand a service request to the executor when one is waiting. The executor
        also gets the node's remaining work (QoS event handlers) every ``others_period_s``.

        Messages are taken from the subscription directly, not through ``executor.spin_once``:
        each ``spin_once`` builds a wait set of every entity of the node in Python (about 3 ms
        under the interpreter lock here), and that lock time, taken while the physics and render
        threads need the lock between their torch calls, inflated the wall time of a step in the
        node (docs/benchmarks.md, "Live node").
        """
        from contextlib import ExitStack

        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

        period = 1.0 / self.input_rate_hz
        services = list(self.services)
        wait_set = _rclpy.WaitSet(1, 0, 0, 0, len(services), 0, self.context.handle)
        next_others = time.monotonic()
        with ExitStack() as held:  # the handles stay valid while this loop waits on them
            for handle in [self.sub_js.handle] + [srv.handle for srv in services]:
                held.enter_context(handle)
            while not stop.is_set() and self.context.ok():
                t0 = time.monotonic()
                if t0 >= next_others:
                    executor.spin_once(timeout_sec=0)
                    next_others = t0 + others_period_s
                wait_set.clear_entities()
                wait_set.add_subscription(self.sub_js.handle)
                for srv in services:
                    wait_set.add_service(srv.handle)
                # at most 0.1 s, so that a stop request is seen promptly
                wait_set.wait(int(min(0.1, max(0.0, next_others - t0)) * 1e9))
                taken = (self.sub_js.handle.take_message(JointState, False)
                         if self.sub_js.handle.pointer in wait_set.get_ready_entities("subscription") else None)
                if wait_set.get_ready_entities("service"):
                    executor.spin_once(timeout_sec=0)
                if taken is not None:
                    self._on_joint_state(*taken)
                    rest = period - (time.monotonic() - t0)
                    if rest > 0:
                        stop.wait(rest)

    # ------------------------------------------------------------------- step
    def _on_step(self) -> None:
        # A reset waits for a running step: a step must not sample the joints before a reset
        # (say, the last trial's pose) and then apply them to the scene the reset brought.
        with self._step_lock:
            self._phase.begin()
            try:
                self._step()
            finally:
                self._phase.end()

    def _after_step(self) -> None:
        """With ``align_to_steps``: wait (at most one step period) until a step ends, so that this
        loop's Python work does not overlap the next step (:class:`~.loops.StepPhase`)."""
        if self.align_to_steps:
            self._phase.after_step(1.0 / self.rate_hz)

    def _step(self) -> None:
        now = self.get_clock().now().nanoseconds
        newest = self.joints.newest_stamp_ns()
        vec = None
        if newest is not None:
            vec = self.joints.sample(min(now, newest))
            self._lag_ms = max(0.0, (now - newest) / 1e6)
            if self._lag_ms > self.max_joint_age * 1e3:
                self.get_logger().warn(f"newest /joint_states is {self._lag_ms / 1e3:.1f} s old: holding the last action",
                                       throttle_duration_sec=5.0)
        try:
            _, ms = self.live.step(vec)
        except Exception as exc:  # noqa: BLE001 - never die on a bad step; report and reset
            self._failure_resets += 1
            self.get_logger().error(f"step failed ({exc}); restarting from the initial scene "
                                    f"({self._failure_resets} such restarts so far)", throttle_duration_sec=2.0)
            try:
                self.live.reset(self.live.template)
                self._set_frame(vec, now)
            except Exception as exc2:  # noqa: BLE001
                self.get_logger().error(f"reset after a failed step failed too ({exc2})", throttle_duration_sec=2.0)
            self._publish_status("restarted_after_failure")
            return
        self._set_frame(vec, now)
        self._step_ms = ms
        self._step_cpu_ms = self.live.last_step_cpu_ms
        self._step_rate.tick()
        self._publish_status("running" if vec is not None else "waiting_for_joint_states")

    def _publish_status(self, state: str) -> None:
        st = SimStatus()
        st.header.stamp = stamp_from_ns(self._frame.stamp_ns)
        st.header.frame_id = self.sim_frame
        st.state = state
        st.step = self.live.steps
        st.num_splats = len(self.live.template)
        st.step_time_ms = float(self._step_ms)
        st.render_time_ms = float(self._render_ms)
        st.step_cpu_ms = float(self._step_cpu_ms)
        st.render_cpu_ms = float(self._render_cpu_ms)
        st.engine_step_ms = float(self.engine.step_ms)
        st.engine_render_ms = float(self.engine.render_ms)
        st.joint_state_lag_ms = float(self._lag_ms)
        st.step_rate_hz = float(self._step_rate.rate())
        st.image_rate_hz = float(self._image_rate.rate())
        st.joint_states_received = self.joints.received
        st.joint_states_rejected = self.joints.rejected
        st.joint_states_dropped = self.joints.dropped
        st.failure_restarts = self._failure_resets
        st.settles = self.live.settles
        self.pub_status.publish(st)

    # ---------------------------------------------------------------- outputs
    def _on_render(self) -> None:
        self._after_step()
        try:
            self._render_and_publish()
        except Exception as exc:  # noqa: BLE001 - a failed render must not stop the executor (and the node)
            self.get_logger().error(f"render failed: {exc}", throttle_duration_sec=5.0)

    def _render_and_publish(self) -> None:
        frame = self._frame  # one step's state, joint state and stamp, taken as a unit
        if frame.joint_vec is None and any(c.mount_link for c in self.live.cameras):
            return  # mounted cameras need a joint state
        t0, c0 = time.perf_counter(), time.thread_time()
        rgb, depth, cams, child_cpu_ms = self._render(frame)
        self._render_ms = (time.perf_counter() - t0) * 1e3
        self._render_cpu_ms = (time.thread_time() - c0) * 1e3 + child_cpu_ms
        stamp = stamp_from_ns(frame.stamp_ns)
        for i, c in enumerate(self.live.cameras):
            frame = camera_frame_id(self.sim_frame, c.name)
            self.pub_img[c.name].publish(image_rgb8(rgb[i], frame, stamp))
            self.pub_depth[c.name].publish(image_depth32(depth[i], frame, stamp))
            self.pub_info[c.name].publish(camera_info(cams.K[i].cpu().numpy(), cams.width, cams.height, frame, stamp))
        self._image_rate.tick()

    def _set_render_scene(self, template) -> None:
        dtype = self.live.state.means.dtype
        self._renderer.set_scene(template.colors().to(dtype), template.opacities.to(dtype))
        self._render_template = template

    def _render(self, frame):
        """(rgb uint8 [C, H, W, 3], depth float32 [C, H, W], cameras, the render process's CPU ms) of
        one step's state: in the render process, or in this thread without one (or after it failed)."""
        if self._renderer is not None:
            from ..live_render import RenderProcessError

            try:
                if frame.template is not self._render_template:  # a reset brought a new scene
                    self._set_render_scene(frame.template)
                cams = self.live.camera_rig(frame.joint_vec)
                res = self._renderer.render(frame.state.means, frame.state.covs, cams)
                return res.rgb, res.depth, cams, res.cpu_ms
            except RenderProcessError as exc:
                self.get_logger().error(f"{exc}: rendering in the node from now on")
                self._renderer.close(timeout_s=0.5)
                self._renderer = None
        out, cams = self.live.render(frame.state, frame.template, frame.joint_vec)
        return out.rgb_u8().cpu().numpy(), out.depth.cpu().numpy(), cams, 0.0

    def _on_splats(self) -> None:
        self._after_step()
        try:
            frame = self._frame
            splats = frame.state.to_splats(frame.template)
            stamp = stamp_from_ns(frame.stamp_ns)
            self.pub_splats.publish(splats_to_cloud(splats, self.sim_frame, stamp))
        except Exception as exc:  # noqa: BLE001 - as for renders
            self.get_logger().error(f"splat publish failed: {exc}", throttle_duration_sec=5.0)

    def _on_tf(self) -> None:
        self._after_step()
        try:
            frame = self._frame  # the robot links of the step the images show, with its stamp
            self.robot_tf.publish(frame.joint_vec, frame.stamp_ns)
        except Exception as exc:  # noqa: BLE001 - as for renders
            self.get_logger().error(f"tf publish failed: {exc}", throttle_duration_sec=5.0)


def main(argv: Optional[list[str]] = None, fast_exit: bool = True) -> int:
    """Run the node until SIGINT / SIGTERM (see :func:`run`). With ``fast_exit`` (the console
    entry point) the process then ends at once with ``os._exit``: everything the node owns is
    closed by then (threads, node, context, log files), and the interpreter's own teardown of
    torch and the extension modules would otherwise take seconds on a busy machine and hold up
    the stop. Pass ``fast_exit=False`` to get the exit status back instead."""
    rc = run(argv)
    if fast_exit:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    return rc


def run(argv: Optional[list[str]] = None) -> int:
    """Spin until SIGINT/SIGTERM; then stop the worker threads while the context is still
    valid (no publish on a dead context), destroy the node and shut down, in that order."""
    import signal

    from rclpy.signals import SignalHandlerOptions

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    rclpy.init(args=argv if argv is not None else sys.argv, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        node = SomaSimNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        node.start()
        node.serve(executor, stop)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ParameterException as exc:
        # a start-up parameter of the wrong type or out of its declared range: a usage error
        print(f"soma_sim_node: error: {_parameter_error(exc)}", file=sys.stderr)
        return 2
    except (FileNotFoundError, ValueError) as exc:
        print(f"soma_sim_node: error: {exc}", file=sys.stderr)
        return 1
    finally:
        if node is not None:
            node.stop()
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


if __name__ == "__main__":
    sys.exit(main())
