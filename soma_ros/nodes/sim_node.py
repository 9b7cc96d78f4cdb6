"""soma_sim_node: the live simulator node (the digital twin on ROS 2).

Topics (prefix from the `topic_prefix` parameter, default /soma):
  sub  /joint_states                  sensor_msgs/JointState (sensor-data QoS; reliable publishers work too)
  pub  <prefix>/splats                sensor_msgs/PointCloud2 (soma_msgs/SplatLayout, packed rgb)
  pub  <prefix>/status                soma_msgs/SimStatus
  srv  <prefix>/reset                 soma_msgs/srv/ResetScene

Start: ``soma_sim_node --ros-args -p scene:=FILE_OR_DIR [-p rate_hz:=30.0]``.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path
from typing import Optional

import rclpy
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState, PointCloud2
from soma_msgs.msg import SimStatus
from soma_msgs.srv import ResetScene

from ..core.splats import Splats
from .conversions import cloud_to_splats_msg, splats_to_cloud
from .qos import JOINT_STATES_QOS, SENSOR_OUT_QOS, STATUS_QOS


def load_scene_file(path: str) -> Splats:
    """A .ply / .splat file, or a scene bundle directory holding splats.ply."""
    p = Path(path)
    if p.is_dir():
        p = p / "splats.ply"
    if not p.is_file():
        raise FileNotFoundError(f"scene file not found: {p}")
    from ..core.ply import load_splats

    s = load_splats(p)
    s.validate()
    return s


class SomaSimNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("soma_sim_node", **kwargs)
        self.declare_parameter("scene", "", ParameterDescriptor(
            description="initial scene: a 3DGS .ply/.splat file or a scene bundle directory (empty: wait for /reset)"))
        self.declare_parameter("checkpoint", "", ParameterDescriptor(description="trained simulator checkpoint (.pt)"))
        self.declare_parameter("rate_hz", 30.0, ParameterDescriptor(
            description="physics step rate, Hz",
            floating_point_range=[FloatingPointRange(from_value=0.5, to_value=1000.0, step=0.0)]))
        self.declare_parameter("sim_frame", "soma_sim", ParameterDescriptor(description="frame of the simulated splats"))
        self.declare_parameter("topic_prefix", "/soma", ParameterDescriptor(description="prefix of published topics and the reset service"))
        prefix = self.get_parameter("topic_prefix").value.rstrip("/")
        self.sim_frame = self.get_parameter("sim_frame").value

        self._lock = threading.Lock()
        self._splats: Optional[Splats] = None
        self._step = 0
        self._js_received = 0
        self._js_rejected = 0

        scene = self.get_parameter("scene").value
        if scene:
            self._splats = load_scene_file(scene)
            self.get_logger().info(f"loaded scene {scene}: {len(self._splats)} splats")

        self._service_group = MutuallyExclusiveCallbackGroup()
        self._step_group = MutuallyExclusiveCallbackGroup()
        self.pub_splats = self.create_publisher(PointCloud2, f"{prefix}/splats", SENSOR_OUT_QOS)
        self.pub_status = self.create_publisher(SimStatus, f"{prefix}/status", STATUS_QOS)
        self.sub_js = self.create_subscription(JointState, "/joint_states", self._on_joint_state, JOINT_STATES_QOS)
        self.srv_reset = self.create_service(ResetScene, f"{prefix}/reset", self._on_reset, callback_group=self._service_group)
        period = 1.0 / float(self.get_parameter("rate_hz").value)
        self.timer = self.create_timer(period, self._on_step, callback_group=self._step_group)

    # ----------------------------------------------------------------- inputs
    def _on_joint_state(self, msg: JointState) -> None:
        self._js_received += 1
        if len(msg.name) != len(msg.position):
            self._js_rejected += 1
            self.get_logger().warn("rejected /joint_states: names and positions differ in length",
                                   throttle_duration_sec=2.0)

    def _on_reset(self, req: ResetScene.Request, resp: ResetScene.Response) -> ResetScene.Response:
        try:
            if req.splats.width * req.splats.height > 0:
                new = cloud_to_splats_msg(req.splats)
            elif req.ply_path:
                new = load_scene_file(req.ply_path)
            else:
                raise ValueError("request has neither splats nor ply_path")
        except (ValueError, FileNotFoundError, OSError) as exc:
            with self._lock:
                resp.num_splats = len(self._splats) if self._splats is not None else 0
            resp.success = False
            resp.message = f"reset refused: {exc}"
            self.get_logger().warn(resp.message)
            return resp
        with self._lock:
            self._splats = new
            self._step = 0
        resp.success = True
        resp.num_splats = len(new)
        resp.message = f"scene reset: {len(new)} splats"
        self.get_logger().info(resp.message)
        return resp

    # ------------------------------------------------------------------- step
    def _on_step(self) -> None:
        t0 = time.perf_counter()
        with self._lock:
            splats = self._splats
            self._step += 1
            step = self._step
        stamp = self.get_clock().now().to_msg()
        status = SimStatus()
        status.header.stamp = stamp
        status.header.frame_id = self.sim_frame
        status.step = step
        status.joint_states_received = self._js_received
        status.joint_states_rejected = self._js_rejected
        if splats is None:
            status.state = "no_scene"
        else:
            status.state = "running"
            status.num_splats = len(splats)
            self.pub_splats.publish(splats_to_cloud(splats, self.sim_frame, stamp))
        status.step_time_ms = (time.perf_counter() - t0) * 1e3
        self.pub_status.publish(status)


def main(argv: Optional[list[str]] = None) -> int:
    rclpy.init(args=argv if argv is not None else sys.argv)
    node = None
    try:
        node = SomaSimNode()
        executor = MultiThreadedExecutor(num_threads=3)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (FileNotFoundError, ValueError) as exc:
        print(f"soma_sim_node: error: {exc}", file=sys.stderr)
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
