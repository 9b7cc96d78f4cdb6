"""`soma view --node`: follow a running soma_sim_node over its ROS topics.

Subscribes (``<p>`` = the node's topic prefix, default /soma):

  <p>/splats                 sensor_msgs/PointCloud2 (soma_msgs splat layout)   best effort, depth 1
  <p>/status                 soma_msgs/SimStatus (step rate, restarts, settles)
  <p>/<cam>/image_raw        sensor_msgs/Image + <p>/<cam>/camera_info          best effort, depth 1
  /<cam>/color/image_raw     the real camera of the same name, when something publishes it
  /joint_states              sensor_msgs/JointState (poses the robot's meshes)
  /tf, /tf_static            camera poses, the robot base and the splats' frame in ``world``
  /robot_description         the URDF (latched), for the robot's meshes

Cameras are found by topic name (every ``<p>/<cam>/image_raw``), so any node's
cameras are shown. Subscriptions are best effort with depth 1 where the node's
writer is reliable keep-last-1: the node never waits for the viewer, and a slow
viewer only skips messages. The view is redrawn at ``draw_hz`` from the newest
messages, only when something new arrived: the splats, status, joint states and
images are taken by the draw thread when it draws (the newest only, never one per
message), and only TF and the robot description go through an executor.
"""

from __future__ import annotations

import os
import re
import tempfile
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np

from .scene import TwinView, default_view_pose, splat_arrays
from .tf_graph import TfGraph

__all__ = ["NodeSource"]


def _image_rgb(msg) -> Optional[np.ndarray]:
    enc = msg.encoding.lower()
    if enc not in ("rgb8", "bgr8"):
        return None
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    buf = np.frombuffer(bytes(msg.data), np.uint8)
    if buf.size < step * h or step < 3 * w:
        return None
    img = buf[: step * h].reshape(h, step)[:, : 3 * w].reshape(h, w, 3)
    return np.ascontiguousarray(img[..., ::-1] if enc == "bgr8" else img)


class NodeSource:
    def __init__(self, view: TwinView, prefix: str = "/soma", draw_hz: float = 10.0, image_hz: float = 5.0,
                 world_frame: str = "world") -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import JointState, PointCloud2
        from soma_msgs.msg import SimStatus
        from std_msgs.msg import String
        from tf2_msgs.msg import TFMessage

        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.view, self.prefix = view, prefix.rstrip("/")
        self.draw_hz, self.image_hz = float(draw_hz), float(image_hz)
        self.world = world_frame
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node("soma_view", context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        # the topics of which only the newest message is drawn are taken by the draw thread
        # itself, from subscriptions on a node no executor spins: a 100 Hz /joint_states or a
        # 30 Hz status costs the viewer nothing between two draws
        self.pull_node = rclpy.create_node("soma_view_pull", context=self.ctx, start_parameter_services=False)
        self._pulled: dict = {}
        self.tf = TfGraph()
        self._latest: dict = {}
        self._seen: dict = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._robot_loaded = False
        self._view_set = False
        self._cams: set[str] = set()
        self._last_images = 0.0
        self.best_effort = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        tf_static_qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                   durability=DurabilityPolicy.TRANSIENT_LOCAL)
        sub = self.node.create_subscription
        self._pull("splats", PointCloud2, f"{self.prefix}/splats", self.best_effort)
        self._pull("status", SimStatus, f"{self.prefix}/status", QoSProfile(depth=10))
        self._pull("joints", JointState, "/joint_states", qos_profile_sensor_data)
        sub(TFMessage, "/tf", self.tf.add, QoSProfile(depth=100))
        sub(TFMessage, "/tf_static", self.tf.add, tf_static_qos)
        sub(String, "/robot_description", self._keep("description"), latched)
        self.node.create_timer(1.0, self._discover)

    def _pull(self, key, msg_type, topic: str, qos) -> None:
        self._pulled[key] = self.pull_node.create_subscription(msg_type, topic, lambda _msg: None, qos)

    def _store(self, key, msg) -> None:
        with self._lock:
            self._latest[key] = msg
            self._seen[key] = self._seen.get(key, 0) + 1

    def _keep(self, key):
        return lambda msg: self._store(key, msg)

    def _discover(self) -> None:
        """Subscribe to every camera the node publishes (and the real one of the same name)."""
        from sensor_msgs.msg import CameraInfo, Image

        pat = re.compile(rf"^{re.escape(self.prefix)}/([^/]+)/image_raw$")
        for topic, _ in self.node.get_topic_names_and_types():
            m = pat.match(topic)
            if not m or m.group(1) in self._cams:
                continue
            cam = m.group(1)
            self._pull(("sim", cam), Image, topic, self.best_effort)
            self._pull(("info", cam), CameraInfo, f"{self.prefix}/{cam}/camera_info", self.best_effort)
            self._pull(("real", cam), Image, f"/{cam}/color/image_raw", self.best_effort)
            self._cams.add(cam)

    # ------------------------------------------------------------------ drawing
    def _newest(self, key):
        """The newest message of a pulled topic (taken now if one arrived), else None."""
        sub = self._pulled.get(key)
        if sub is not None:
            with sub.handle:
                while (got := sub.handle.take_message(sub.msg_type, False)) is not None:
                    self._store(key, got[0])
        return self._latest.get(key)

    def _take(self, key, seen_before: dict):
        self._newest(key)
        with self._lock:
            n = self._seen.get(key, 0)
            msg = self._latest.get(key)
        if msg is None or seen_before.get(key) == n:
            return None
        seen_before[key] = n
        return msg

    def _load_robot(self, description: str) -> None:
        """The URDF from /robot_description; its mesh references are absolute file:// URIs."""
        import xml.etree.ElementTree as ET

        root = ET.fromstring(description)
        base = root.find("link").get("name")  # a URDF's root is its first link for robot_state_publisher's trees
        children = {j.find("child").get("link") for j in root.iter("joint") if j.find("child") is not None}
        base = next((lk.get("name") for lk in root.iter("link") if lk.get("name") not in children), base)
        T = self.tf.lookup(base, self.world)
        if T is None:
            return  # wait for the base's transform
        f = Path(tempfile.mkdtemp(prefix="soma_view_")) / "robot_description.urdf"
        f.write_text(description)
        self.view.set_robot(f, T)
        self._robot_base = T
        self._robot_loaded = True

    def _draw(self, seen: dict) -> None:
        from ..core.cloud_layout import cloud_to_splats

        desc = self._latest.get("description")
        if desc is not None and not self._robot_loaded:
            try:
                self._load_robot(desc.data)
            except Exception as exc:  # noqa: BLE001 - a robot that cannot be drawn leaves the rest
                self._robot_loaded = True
                self.node.get_logger().warn(f"/robot_description cannot be drawn: {exc}")
        cloud = self._take("splats", seen)
        if cloud is not None:
            splats = cloud_to_splats(cloud)
            T = self.tf.lookup(cloud.header.frame_id, self.world)
            self.view.set_splats(*splat_arrays(splats, T))
            if not self._view_set:
                m = splats.means.double().numpy()
                m = m if T is None else m @ T[:3, :3].T + T[:3, 3]
                base = getattr(self, "_robot_base", None)
                target, eye = default_view_pose(m.mean(0), None if base is None else base[:3, 3], np.array([0, 0, 1.0]),
                                                radius=float(np.linalg.norm(m - m.mean(0), axis=1).max()))
                self.view.look_at(target, eye)
                self._view_set = True
        js = self._take("joints", seen)
        if js is not None:
            self.view.set_joints(list(js.name), list(js.position))
        now = time.monotonic()
        if self.image_hz > 0 and now - self._last_images >= 1.0 / self.image_hz:
            self._last_images = now
            for cam in sorted(self._cams):
                sim, info = self._take(("sim", cam), seen), self._newest(("info", cam))
                if sim is None or info is None:
                    continue
                T = self.tf.lookup(info.header.frame_id, self.world)
                if T is None:
                    continue
                real = self._newest(("real", cam))
                self.view.set_camera(cam, np.array(info.k).reshape(3, 3), info.width, info.height, T,
                                     sim_image=_image_rgb(sim), real_image=None if real is None else _image_rgb(real))
        st = self._take("status", seen)
        if st is not None:
            self.view.set_status({"mode": f"node ({self.prefix})", "state": st.state, "splats": st.num_splats,
                                  "steps": st.step, "step rate (Hz)": f"{st.step_rate_hz:.1f}",
                                  "image rate (Hz)": f"{st.image_rate_hz:.1f}", "restarts": st.failure_restarts,
                                  "settles": st.settles, "step time (ms)": f"{st.step_time_ms:.1f}"})

    # ------------------------------------------------------------------ threads
    def start(self) -> None:
        def spin() -> None:
            while not self._stop.is_set() and self.ctx.ok():
                self.executor.spin_once(timeout_sec=0.1)

        def draw() -> None:
            seen: dict = {}
            period = 1.0 / self.draw_hz
            while not self._stop.is_set():
                t0 = time.monotonic()
                try:
                    self._draw(seen)
                except Exception as exc:  # noqa: BLE001 - a bad message must not stop the view
                    self.node.get_logger().warn(f"draw failed: {exc}", throttle_duration_sec=5.0)
                self._stop.wait(max(0.0, period - (time.monotonic() - t0)))

        for name, fn in (("soma_view_spin", spin), ("soma_view_draw", draw)):
            t = threading.Thread(target=fn, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        self.executor.shutdown()
        self.pull_node.destroy_node()
        self.node.destroy_node()
        if self.ctx.ok():
            import rclpy

            rclpy.shutdown(context=self.ctx)
