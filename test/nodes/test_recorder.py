"""The recorder as its own OS process records what the test publishes; the bag reads back
with rosbags' AnyReader with identical content."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np

RECORDER = "soma_ros.nodes.recorder"
IMG_TOPIC, CLOUD_TOPIC, STATUS_TOPIC, INFO_TOPIC = (
    "/camera/color/image_raw", "/soma/splats", "/soma/status", "/soma/camera_info")


def _image(k: int):
    from sensor_msgs.msg import Image
    from std_msgs.msg import Header
    from builtin_interfaces.msg import Time

    rgb = np.random.default_rng(k).integers(0, 256, size=(240, 320, 3), dtype=np.uint8)
    return Image(header=Header(stamp=Time(sec=100 + k, nanosec=k), frame_id="soma_camera"), height=240, width=320,
                 encoding="rgb8", is_bigendian=0, step=960, data=rgb.tobytes())


def _cloud(k: int):
    from builtin_interfaces.msg import Time

    from soma_ros.core.scenes import synthetic_rope
    from soma_ros.nodes.conversions import splats_to_cloud

    return splats_to_cloud(synthetic_rope(400 + 100 * k, seed=k), "soma_sim", Time(sec=7, nanosec=k))


def _status(k: int):
    from soma_msgs.msg import SimStatus

    s = SimStatus(state="running", step=k, num_splats=1234, step_time_ms=1.25 * k, render_time_ms=3.5,
                  joint_state_lag_ms=0.5, step_rate_hz=30.0, image_rate_hz=10.0,
                  joint_states_received=10 * k, joint_states_rejected=k // 2, failure_restarts=k % 3, settles=k % 2)
    s.header.frame_id = "soma_sim"
    s.header.stamp.sec = 50 + k
    return s


def _camera_info():
    from builtin_interfaces.msg import Time

    from soma_ros.nodes.conversions import camera_info

    K = np.array([[300.0, 0, 160.0], [0, 300.0, 120.0], [0, 0, 1]])
    return camera_info(K, 320, 240, "soma_camera", Time(sec=1))


def _read_bag(path: Path):
    """{topic: [(log time, raw, rosbags message)]}, {topic: connection} read back with AnyReader."""
    from rosbags.highlevel import AnyReader

    from soma_ros.bagtypes import typestore

    got: dict = {}
    conns: dict = {}
    with AnyReader([path], default_typestore=typestore()) as reader:
        for conn in reader.connections:
            conns[conn.topic] = conn
        for conn, t, raw in reader.messages():
            got.setdefault(conn.topic, []).append((t, bytes(raw), reader.deserialize(raw, conn.msgtype)))
    return got, conns


def _wait_matched(executor, publishers, timeout=30.0):
    from soma_ros.nodes.testing import spin_until

    return spin_until(executor, lambda: all(p.get_subscription_count() >= 1 for p in publishers), timeout)


def test_recorder_writes_what_was_published(tmp_path, ros_env, ros_context, ros_executor):
    from rclpy.duration import Duration
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message
    from rosbags.interfaces import QosDurability, QosReliability
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2
    from soma_msgs.msg import SimStatus

    from soma_ros.nodes.rosbags_bridge import to_rclpy
    from soma_ros.nodes.testing import RosProcess

    node = Node("recorder_test_talker", context=ros_context)
    ros_executor.add_node(node)
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pubs = {
        IMG_TOPIC: node.create_publisher(Image, IMG_TOPIC, reliable),
        CLOUD_TOPIC: node.create_publisher(PointCloud2, CLOUD_TOPIC, reliable),
        STATUS_TOPIC: node.create_publisher(SimStatus, STATUS_TOPIC, reliable),
        INFO_TOPIC: node.create_publisher(CameraInfo, INFO_TOPIC, latched),
    }
    # Latched: published before the recorder exists, recorded all the same (transient local followed).
    info = _camera_info()
    pubs[INFO_TOPIC].publish(info)

    sent = {IMG_TOPIC: [_image(k) for k in range(12)], CLOUD_TOPIC: [_cloud(k) for k in range(3)],
            STATUS_TOPIC: [_status(k) for k in range(5)]}
    bag = tmp_path / "rec"
    with RosProcess(RECORDER, ["--out", str(bag), "--topics", IMG_TOPIC, CLOUD_TOPIC, STATUS_TOPIC, INFO_TOPIC],
                    ros_env, name="recorder") as rec:
        assert _wait_matched(ros_executor, pubs.values()), rec.output()
        t_before = node.get_clock().now().nanoseconds
        for k in range(12):  # interleaved, as a simulator would publish
            pubs[IMG_TOPIC].publish(sent[IMG_TOPIC][k])
            if k % 4 == 0:
                pubs[CLOUD_TOPIC].publish(sent[CLOUD_TOPIC][k // 4])
            if k < 5:
                pubs[STATUS_TOPIC].publish(sent[STATUS_TOPIC][k])
        for topic, p in pubs.items():  # the recorder's reader holds everything...
            assert p.wait_for_all_acked(Duration(seconds=20)), f"{topic} not acknowledged\n{rec.output()}"
        t_after = node.get_clock().now().nanoseconds
        os.killpg(rec.proc.pid, signal.SIGINT)  # ...and SIGINT drains it into the bag before closing
        rc = rec.wait(timeout=20)
        out = rec.output()
    assert rc == 0, out
    m = re.search(r"wrote (\d+) messages", out)
    assert m and int(m.group(1)) == 12 + 3 + 5 + 1, out
    assert "[sqlite3]" in out

    got, conns = _read_bag(bag)
    classes = {IMG_TOPIC: Image, CLOUD_TOPIC: PointCloud2, STATUS_TOPIC: SimStatus, INFO_TOPIC: CameraInfo}
    sent[INFO_TOPIC] = [info]
    for topic, msgs in sent.items():
        rows = got.get(topic, [])
        assert len(rows) == len(msgs), (topic, len(rows))
        for k, ((t, raw, decoded), expect) in enumerate(zip(rows, msgs)):
            # Byte level: the recorded CDR decodes to the published message; so does rosbags' decoding.
            assert deserialize_message(raw, classes[topic]) == expect, (topic, k)
            assert to_rclpy(decoded) == expect, (topic, k)
        times = [t for t, _, _ in rows]
        assert times == sorted(times), topic
        if topic != INFO_TOPIC:  # the latched one arrived before t_before
            assert t_before <= times[0] and times[-1] <= t_after + 10**9, topic
    # Spot checks of the rosbags side (definitions embedded in the bag, soma_msgs included).
    img = got[IMG_TOPIC][3][2]
    assert img.data.dtype == np.uint8 and img.data.tobytes() == bytes(sent[IMG_TOPIC][3].data)
    st = got[STATUS_TOPIC][4][2]
    assert (st.state, st.step, st.joint_states_rejected, st.__msgtype__) == ("running", 4, 2, "soma_msgs/msg/SimStatus")
    assert conns[STATUS_TOPIC].msgtype == "soma_msgs/msg/SimStatus"
    assert "SimStatus" in conns[STATUS_TOPIC].msgdef.data or "step_time_ms" in conns[STATUS_TOPIC].msgdef.data
    # The publishers' QoS is kept in the bag's metadata.
    assert conns[IMG_TOPIC].ext.offered_qos_profiles[0].reliability == QosReliability.RELIABLE
    assert conns[INFO_TOPIC].ext.offered_qos_profiles[0].durability == QosDurability.TRANSIENT_LOCAL


def test_recorder_mcap_typed_topic_and_max_messages(tmp_path, ros_env, ros_context, ros_executor):
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from soma_msgs.msg import SimStatus

    from soma_ros.nodes.testing import RosProcess, spin_until

    node = Node("recorder_test_talker2", context=ros_context)
    ros_executor.add_node(node)
    pub = node.create_publisher(SimStatus, STATUS_TOPIC, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    bag = tmp_path / "rec_mcap"
    with RosProcess(RECORDER, ["--out", str(bag), "--storage", "mcap", "--max-messages", "5", "--duration", "60",
                               "--topics", f"{STATUS_TOPIC}:soma_msgs/msg/SimStatus"], ros_env, name="recorder") as rec:
        assert _wait_matched(ros_executor, [pub]), rec.output()
        for k in range(8):
            pub.publish(_status(k))
        # It stops by itself after 5 messages.
        assert spin_until(ros_executor, lambda: not rec.alive(), 30), rec.output()
        rc = rec.wait(timeout=5)
        out = rec.output()
    assert rc == 0, out
    assert "wrote 5 messages" in out and "[mcap]" in out, out
    assert (bag / "rec_mcap.mcap").is_file()
    got, _ = _read_bag(bag)
    assert [m.step for _, _, m in got[STATUS_TOPIC]] == [0, 1, 2, 3, 4]


def test_recorder_errors_are_one_line(tmp_path, ros_env):
    existing = tmp_path / "exists"
    existing.mkdir()
    cases = [
        (["--out", str(tmp_path / "a"), "--topics", "/not_published", "--discovery-timeout", "1"],
         "topic /not_published not found in the ROS graph within 1 s"),
        (["--out", str(tmp_path / "b"), "--topics", "/x:nope_msgs/msg/Nothing"], "no Python package 'nope_msgs'"),
        (["--out", str(existing), "--topics", STATUS_TOPIC], "output bag already exists"),
    ]
    procs = [(subprocess.Popen([sys.executable, "-m", RECORDER, *args], env=ros_env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True), expect) for args, expect in cases]
    for proc, expect in procs:
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 1, (expect, out, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("soma_recorder: error: ") and expect in lines[0], err
    assert not (tmp_path / "a").exists(), "a failed recording left a bag behind"


def test_player_into_recorder_round_trip(tmp_path, ros_env):
    """soma_bag_player -> soma_recorder, two OS processes: the recorded bag holds the played
    stream with its timing (receive stamps spaced by the bag's gaps / rate), keeps the latched
    topic's QoS, and plays back again."""
    from rosbags.interfaces import QosDurability

    from soma_ros.nodes.testing import RosProcess
    from test_bag_player import BAG_SPAN_S, JS_HZ, JS_N, js_position, write_bag

    src = write_bag(tmp_path / "src")
    out = tmp_path / "recorded"
    rate = 2.0
    with RosProcess("soma_ros.nodes.bag_player", [str(src), "--rate", str(rate), "--wait-for-subscribers", "1",
                                                  "--topics", "/joint_states", "/robot_description"],
                    ros_env, name="player") as player, \
         RosProcess(RECORDER, ["--out", str(out), "--topics", "/joint_states", "/robot_description",
                               "--max-messages", str(JS_N + 1), "--duration", "40"], ros_env, name="recorder") as rec:
        assert rec.wait(timeout=60) == 0, rec.output() + player.output()
        assert player.wait(timeout=30) == 0, player.output()
    got, conns = _read_bag(out)
    js = got["/joint_states"]
    assert len(js) == JS_N
    assert np.allclose([m.position for _, _, m in js], [js_position(k) for k in range(JS_N)])
    assert [m.data for _, _, m in got["/robot_description"]] == ["<robot name='panda'/>"]
    assert conns["/robot_description"].ext.offered_qos_profiles[0].durability == QosDurability.TRANSIENT_LOCAL
    times = np.array([t for t, _, _ in js], dtype=np.int64)
    span = (times[-1] - times[0]) / 1e9
    assert 0.9 * BAG_SPAN_S / rate <= span <= 1.5 * BAG_SPAN_S / rate, span
    gaps_ms = np.diff(times) / 1e6
    assert np.median(np.abs(gaps_ms - 1e3 / JS_HZ / rate)) < 8.0, np.round(gaps_ms, 1).tolist()

    # The recorded bag is itself playable (definitions and QoS as the player expects them).
    again = subprocess.run([sys.executable, "-m", "soma_ros.nodes.bag_player", str(out), "--rate", "8",
                            "--topics", "/joint_states", "/robot_description"],
                           env=ros_env, capture_output=True, text=True, timeout=60)
    assert again.returncode == 0, again.stdout + again.stderr
    assert f"/joint_states {JS_N}, /robot_description 1" in again.stdout, again.stdout
