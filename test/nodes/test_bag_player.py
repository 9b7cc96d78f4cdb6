"""soma_bag_player as its own OS process, heard by a subscriber in the test's rclpy context.

The bag is written here with rosbags: 60 JointState messages at 30 Hz (the 9
Panda joints), 10 camera Images at 5 Hz, a latched /robot_description, a
/tf_static and the world's ground-truth /world/object_points (never played).
"""

from __future__ import annotations

import importlib.util
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)] + ["panda_finger_joint1", "panda_finger_joint2"]
T0_NS = 1_700_000_000_000_000_000
JS_N, JS_HZ = 60, 30.0
IMG_N, IMG_HZ, IMG_W, IMG_H = 10, 5.0, 160, 120
LATENCY_NS = 2_000_000  # recorded header stamps lag the receive time by 2 ms
BAG_SPAN_S = (JS_N - 1) / JS_HZ  # 1.967 s: the last message of the bag is a JointState
PLAYER = "soma_ros.nodes.bag_player"


def js_time(k: int) -> int:
    return T0_NS + int(round(k * 1e9 / JS_HZ))


def img_time(k: int) -> int:
    return T0_NS + 5_000_000 + int(round(k * 1e9 / IMG_HZ))


def js_position(k: int) -> list[float]:
    return [0.01 * k + 0.1 * j for j in range(len(PANDA_JOINTS))]


def img_pixels(k: int) -> np.ndarray:
    rng = np.random.default_rng(k)
    return rng.integers(0, 256, size=IMG_H * IMG_W * 3, dtype=np.uint8)


def write_bag(path: Path) -> Path:
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    from rosbags.rosbag2 import Writer

    from soma_ros.bagtypes import typestore

    ts = typestore()
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]
    Header = T["std_msgs/msg/Header"]

    def header(ns: int, frame: str):
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    latched = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, QosTime(0, 0),
                  QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)
    with Writer(path, version=9) as w:
        c_js = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        c_img = w.add_connection("/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        c_desc = w.add_connection("/robot_description", "std_msgs/msg/String", typestore=ts,
                                  offered_qos_profiles=[latched])
        c_tf = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        c_gt = w.add_connection("/world/object_points", "sensor_msgs/msg/PointCloud2", typestore=ts)

        w.write(c_desc, T0_NS, ts.serialize_cdr(T["std_msgs/msg/String"](data="<robot name='panda'/>"),
                                                "std_msgs/msg/String"))
        tf = T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](
            header=header(0, "world"), child_frame_id="camera_link",
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=1.0, y=0.0, z=0.5),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))])
        w.write(c_tf, T0_NS, ts.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))
        gt = T["sensor_msgs/msg/PointCloud2"](header=header(T0_NS, "world"), height=1, width=0, fields=[],
                                              is_bigendian=False, point_step=0, row_step=0,
                                              data=np.zeros(0, np.uint8), is_dense=True)
        msgs = []
        for k in range(JS_N):
            t = js_time(k)
            js = T["sensor_msgs/msg/JointState"](header=header(t - LATENCY_NS, ""), name=PANDA_JOINTS,
                                                 position=np.array(js_position(k)),
                                                 velocity=np.zeros(9), effort=np.zeros(0))
            msgs.append((t, c_js, ts.serialize_cdr(js, "sensor_msgs/msg/JointState")))
            msgs.append((t + 1, c_gt, ts.serialize_cdr(gt, "sensor_msgs/msg/PointCloud2")))
        for k in range(IMG_N):
            t = img_time(k)
            img = T["sensor_msgs/msg/Image"](header=header(t - LATENCY_NS, "camera_color_optical_frame"),
                                             height=IMG_H, width=IMG_W, encoding="rgb8", is_bigendian=0,
                                             step=IMG_W * 3, data=img_pixels(k))
            msgs.append((t, c_img, ts.serialize_cdr(img, "sensor_msgs/msg/Image")))
        for t, c, raw in sorted(msgs, key=lambda m: m[0]):
            w.write(c, t, raw)
    return path


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    return write_bag(tmp_path_factory.mktemp("player") / "bag")


def _ns(stamp) -> int:
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


# The Listener subscribes /joint_states twice (reliable and sensor QoS); the player waits for both. With 1 it
# could start once the first was matched, before the graph showed the second, which then missed the first
# messages (a clean-clone run under load: the reliable subscription's first message was the 58th).
LISTENER_JS_SUBS = "2"


class Listener:
    """Subscriptions of the test: reliable /joint_states and images, a sensor-QoS /joint_states
    (as soma_sim_node subscribes), a latched /robot_description."""

    def __init__(self, context) -> None:
        from rclpy.node import Node
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import Image, JointState
        from std_msgs.msg import String

        self.node = Node("bag_player_test_listener", context=context)
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.reset()
        self.node.create_subscription(JointState, "/joint_states", self._on("js"), reliable)
        # The simulator's sensor QoS (best effort, volatile), with a history deep enough for the whole stream:
        # at the stock depth of 5 a test process that fell behind on a loaded machine lost 11 of 60 to its own
        # history, which says nothing about the player. Depth is the reader's own and does not affect matching.
        sensor = QoSProfile(depth=100, reliability=qos_profile_sensor_data.reliability,
                            durability=qos_profile_sensor_data.durability)
        self.node.create_subscription(JointState, "/joint_states", self._on("js_sensor"), sensor)
        self.node.create_subscription(Image, "/camera/color/image_raw", self._on("img"), reliable)
        self.node.create_subscription(String, "/robot_description", self._on("desc"), latched)

    def reset(self) -> None:
        self.got: dict[str, list] = {"js": [], "js_sensor": [], "img": [], "desc": []}
        self.publishers_seen: dict[str, list] = {}

    def _on(self, key: str):
        return lambda msg: self.got[key].append((time.monotonic(), msg))

    def watch_graph(self) -> None:
        for topic in ("/robot_description", "/world/object_points"):
            infos = self.node.get_publishers_info_by_topic(topic)
            if infos:
                self.publishers_seen[topic] = infos


def _play(listener, executor, env, args, n_js=JS_N, n_img=0, timeout=40.0):
    from soma_ros.nodes.testing import RosProcess, spin_until

    listener.reset()
    with RosProcess(PLAYER, args, env, name="player") as proc:
        def done() -> bool:
            listener.watch_graph()
            return (not proc.alive() and len(listener.got["js"]) >= n_js and len(listener.got["img"]) >= n_img)

        ok = spin_until(executor, done, timeout)
        # Anything still in flight after the player exits.
        spin_until(executor, lambda: False, 0.2)
        out = proc.output()
        assert ok, f"player did not deliver in {timeout} s: js={len(listener.got['js'])} " \
                   f"img={len(listener.got['img'])}\n{out}"
        rc = proc.wait(timeout=10)
    assert rc == 0, out
    m = re.search(r"in ([0-9.]+) s wall for ([0-9.]+) s of bag: achieved rate ([0-9.]+)x", out)
    assert m, out
    return out, float(m.group(1)), float(m.group(3))


def test_player_plays_with_original_timing_scaled_by_rate(bag, ros_env, ros_context, ros_executor):
    from rclpy.qos import DurabilityPolicy

    listener = Listener(ros_context)
    ros_executor.add_node(listener.node)

    # --- rate 2.0, restamped (default), cameras and the latched description too
    out, wall2, achieved2 = _play(listener, ros_executor, ros_env, [
        str(bag), "--rate", "2.0", "--wait-for-subscribers", LISTENER_JS_SUBS, "--cameras",
        "--topics", "/joint_states", "/robot_description", "--ros-args", "-r", "__node:=player_under_test",
    ], n_img=IMG_N)
    js = listener.got["js"]
    assert len(js) == JS_N, out
    for k, (_, msg) in enumerate(js):  # all, in order, with the right content
        assert list(msg.name) == PANDA_JOINTS
        assert np.allclose(msg.position, js_position(k)), (k, list(msg.position))
        assert len(msg.velocity) == 9 and len(msg.effort) == 0
    # The sensor-QoS (best effort) subscriber of the simulator's kind hears the same stream, in order;
    # best effort may drop a sample (seen once: the first, on a loaded machine), so up to 2 may be missing.
    reliable = [list(m.position) for _, m in js]
    sensor = [list(m.position) for _, m in listener.got["js_sensor"]]
    it = iter(reliable)
    assert all(p in it for p in sensor), "the best-effort stream is not the reliable one's, in order"
    assert len(sensor) >= JS_N - 2, f"best-effort subscriber heard {len(sensor)} of {JS_N}"

    imgs = listener.got["img"]
    assert len(imgs) == IMG_N
    for k, (_, msg) in enumerate(imgs):
        assert (msg.width, msg.height, msg.encoding, msg.step) == (IMG_W, IMG_H, "rgb8", IMG_W * 3)
        assert msg.header.frame_id == "camera_color_optical_frame"
        assert bytes(msg.data) == img_pixels(k).tobytes(), f"image {k} content differs"

    # Latched topic: offered transient local, delivered once; ground truth never published.
    assert [m.data for _, m in listener.got["desc"]] == ["<robot name='panda'/>"]
    assert listener.publishers_seen.get("/robot_description"), "player's /robot_description publisher never seen"
    assert all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
               for i in listener.publishers_seen["/robot_description"])
    assert "/world/object_points" not in listener.publishers_seen

    # Timing, from the restamped header stamps (= publish times - the recorded 2 ms latency):
    stamps = np.array([_ns(m.header.stamp) for _, m in js], dtype=np.int64)
    now_ns = listener.node.get_clock().now().nanoseconds
    assert abs(now_ns - stamps[-1]) < 10e9, "restamped stamps are not near the current time"
    assert np.all(np.diff(stamps) > 0)
    span2 = (stamps[-1] - stamps[0]) / 1e9
    expected2 = BAG_SPAN_S / 2.0
    assert 0.95 * expected2 <= span2 <= 1.5 * expected2, f"stamp span {span2:.3f} s, expected {expected2:.3f} s"
    gaps_ms = np.diff(stamps) / 1e6
    median_err = statistics.median(abs(g - 1e3 / JS_HZ / 2.0) for g in gaps_ms)
    assert median_err < 8.0, f"median gap error {median_err:.1f} ms: {np.round(gaps_ms, 1).tolist()}"
    # Images and joint states keep their relative timing (image k is due at 5 ms + k * 200 ms, / 2).
    img_stamps = np.array([_ns(m.header.stamp) for _, m in imgs], dtype=np.int64)
    rel = (img_stamps - stamps[0]) / 1e9
    assert np.all(np.abs(rel - (np.array([img_time(k) for k in range(IMG_N)]) - T0_NS) / 2e9) < 0.25), rel
    assert 0.95 * expected2 <= wall2 <= 1.5 * expected2, out
    assert 1.5 <= achieved2 <= 2.1, out
    arrival2 = js[-1][0] - js[0][0]

    # --- rate 1.0, original stamps kept: about twice as long
    out, wall1, achieved1 = _play(listener, ros_executor, ros_env, [
        str(bag), "--rate", "1.0", "--wait-for-subscribers", LISTENER_JS_SUBS, "--no-restamp"])
    js = listener.got["js"]
    assert len(js) == JS_N, out
    assert [_ns(m.header.stamp) for _, m in js] == [js_time(k) - LATENCY_NS for k in range(JS_N)]
    assert listener.got["img"] == [], "images played without --cameras"
    assert 0.95 * BAG_SPAN_S <= wall1 <= 1.5 * BAG_SPAN_S, out
    assert 0.75 <= achieved1 <= 1.05, out
    arrival1 = js[-1][0] - js[0][0]
    assert 1.4 <= wall1 / wall2 <= 2.6, (wall1, wall2)
    assert 1.4 <= arrival1 / arrival2 <= 2.8, (arrival1, arrival2)


def test_start_offset_skips_the_beginning(bag, ros_env, ros_context, ros_executor):
    listener = Listener(ros_context)
    ros_executor.add_node(listener.node)
    # Skip the first second at 4x: JointStates 30..59 remain (t >= 1.0 s), ~0.24 s of playback.
    first = int(np.ceil(1.0 * JS_HZ))
    out, wall, _ = _play(listener, ros_executor, ros_env, [
        str(bag), "--rate", "4.0", "--start-offset", "1.0", "--wait-for-subscribers", LISTENER_JS_SUBS,
        "--topics", "/joint_states", "/robot_description"], n_js=JS_N - first)
    got = [list(m.position) for _, m in listener.got["js"]]
    assert len(got) == JS_N - first, out
    assert np.allclose(got, [js_position(k) for k in range(first, JS_N)])
    # The latched description was recorded before the offset: it is published at the start anyway.
    assert [m.data for _, m in listener.got["desc"]] == ["<robot name='panda'/>"]
    assert wall <= 1.0, out


def _run_player(args, env, timeout=60):
    return subprocess.run([sys.executable, "-m", PLAYER, *args], env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_errors_are_one_line(bag, tmp_path, ros_env):
    cases = [
        ([str(tmp_path / "no_such_bag")], "bag not found"),
        ([str(bag), "--topics", "/no_such_topic"], "topic /no_such_topic not in the bag"),
        ([str(bag), "--topics", "/world/object_points"], "ground truth and is never played"),
        ([str(tmp_path)], "cannot open bag"),
    ]
    if importlib.util.find_spec("tf2_msgs") is None:
        cases.append(([str(bag), "--tf-static"], "no Python package 'tf2_msgs'"))
    procs = [(subprocess.Popen([sys.executable, "-m", PLAYER, *args], env=ros_env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True), expect) for args, expect in cases]
    for proc, expect in procs:
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 1, (expect, out, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("soma_bag_player: error: ") and expect in lines[0], err
        assert out == ""


def test_loop_repeats_until_interrupted(bag, ros_env, ros_context, ros_executor):
    import os
    import signal

    from soma_ros.nodes.testing import RosProcess, spin_until

    listener = Listener(ros_context)
    ros_executor.add_node(listener.node)
    want = 2 * JS_N + 10
    with RosProcess(PLAYER, [str(bag), "--rate", "8", "--loop", "--wait-for-subscribers", LISTENER_JS_SUBS], ros_env,
                    name="player") as proc:
        ok = spin_until(ros_executor, lambda: len(listener.got["js"]) >= want or not proc.alive(), 40)
        assert ok and proc.alive(), proc.output()
        os.killpg(proc.proc.pid, signal.SIGINT)
        rc = proc.wait(timeout=20)
        out = proc.output()
    assert rc == 0, out
    assert re.search(r"published \d+ messages .* \d+ loops", out), out
    js = listener.got["js"][:want]
    expected = [js_position(k % JS_N) for k in range(want)]
    assert np.allclose([list(m.position) for _, m in js], expected)
    stamps = [_ns(m.header.stamp) for _, m in js]
    assert all(b > a for a, b in zip(stamps, stamps[1:])), "restamped stamps must keep increasing across loops"
    # The seam between passes keeps the rhythm: one mean gap (33.3 ms / 8), not a burst or a pause.
    seam_ms = (stamps[JS_N] - stamps[JS_N - 1]) / 1e6
    assert 2.0 <= seam_ms <= 100.0, seam_ms


def test_restamp_reaches_every_nested_header():
    """Like tf2_msgs/TFMessage (a list of stamped transforms), a MarkerArray holds one header per
    element: restamping must find them all, and leave header-less types alone."""
    from sensor_msgs.msg import Image, PointField
    from visualization_msgs.msg import Marker, MarkerArray

    from soma_ros.nodes.bag_player import _header_walker

    cache: dict = {}
    arr = MarkerArray(markers=[Marker(id=i) for i in range(3)])
    seen = []
    _header_walker(MarkerArray, cache)(arr, lambda h: (seen.append(h), setattr(h.stamp, "sec", 42)))
    # Jazzy's Marker has its own header and a CompressedImage texture with another one.
    assert len(seen) == 6 and all(m.header.stamp.sec == 42 and m.texture.header.stamp.sec == 42 for m in arr.markers)
    img = Image()
    _header_walker(Image, cache)(img, lambda h: setattr(h, "frame_id", "x"))
    assert img.header.frame_id == "x"
    assert _header_walker(PointField, cache) is None
