"""What stock ROS tools expect of soma_ros's outputs, checked with their own rules.

* depth_image_proc's rule (a depth pixel makes a point iff ``std::isfinite(depth)``,
  then ``(u - cx) z / fx, (v - cy) z / fy, z``) gives no point at the camera origin;
* every frame_id in a reference-world bag and on the live node's topics reaches
  ``world`` through TF (``/tf_static`` + ``/tf``), in one tree;
* ``/robot_description`` is latched (a subscriber that joins late receives it) and names
  meshes that exist;
* the ``mcap`` reader with ``mcap-ros2-support`` (an independent CDR decoder) decodes
  every message of a world bag.
"""

from __future__ import annotations

from pathlib import Path
from urllib.parse import urlparse

import numpy as np
import pytest

from conftest import sim_node_args
from soma_ros.nodes.testing import RosProcess

START_TIMEOUT = 90.0


def depth_image_proc_points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """depth_image_proc point_cloud_xyz (depth_conversions.hpp convertDepth) for 32FC1:
    points [N, 3] of the pixels whose depth is finite."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    ok = np.isfinite(depth)
    z = depth[ok].astype(np.float64)
    x = (u[ok] - K[0, 2]) * z / K[0, 0]
    y = (v[ok] - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=1)


def tf_parents(messages) -> dict[str, str]:
    """{child: parent} over TFMessages; a child with two parents fails (two trees / a loop)."""
    parents: dict[str, str] = {}
    for msg in messages:
        for t in msg.transforms:
            old = parents.setdefault(t.child_frame_id, t.header.frame_id)
            assert old == t.header.frame_id, f"frame {t.child_frame_id} has parents {old} and {t.header.frame_id}"
    return parents


def reaches(frame: str, parents: dict[str, str], root: str = "world") -> bool:
    seen = set()
    while frame != root:
        if frame in seen or frame not in parents:
            return False
        seen.add(frame)
        frame = parents[frame]
    return True


def frame_ids(msg) -> set[str]:
    """Every header.frame_id / child_frame_id in a decoded message (any decoder)."""
    out = set()
    header = getattr(msg, "header", None)
    if header is not None and getattr(header, "frame_id", ""):
        out.add(header.frame_id)
    for t in getattr(msg, "transforms", None) or []:
        out |= {t.header.frame_id, t.child_frame_id}
    return out


# --------------------------------------------------------------------------- depth rule
def test_depth_image_proc_rule_on_the_32fc1_conversion():
    """Where the renderer draws nothing (depth exactly 0) the 32FC1 image holds NaN, so the
    isfinite rule makes no point at the camera origin; drawn pixels keep their depth."""
    from builtin_interfaces.msg import Time

    from soma_ros.nodes.conversions import image_depth32

    d = np.zeros((6, 8), np.float32)
    d[2:4, 3:6] = 0.8
    d[0, 0] = -np.inf
    msg = image_depth32(d, "cam", Time())
    back = np.frombuffer(bytes(msg.data), np.float32).reshape(6, 8)
    assert np.array_equal(back[2:4, 3:6], d[2:4, 3:6])
    assert np.isnan(back[d <= 0]).all()
    K = np.array([[100.0, 0, 4], [0, 100.0, 3], [0, 0, 1]])
    pts = depth_image_proc_points(back, K)
    assert len(pts) == 6 and np.linalg.norm(pts, axis=1).min() > 0.79
    # the old "0 = nothing" would have given 42 points at the origin
    assert (np.linalg.norm(depth_image_proc_points(np.where(d < 0, 0, d), K), axis=1) == 0).sum() == 42


# --------------------------------------------------------------------------- world bag
@pytest.fixture(scope="module")
def world_bag(tmp_path_factory) -> Path:
    """One tiny reference-world rope episode of 8 frames, stored as MCAP."""
    from soma_ros.world import generate_dataset, load_world_config

    out = tmp_path_factory.mktemp("world_mcap")
    generate_dataset(load_world_config(), "rope", "tiny", out, episodes=1, seed=5, frames=8, progress=False,
                     storage="mcap")
    bags = [p for p in out.iterdir() if p.is_dir()]
    assert len(bags) == 1
    return bags[0]


def mcap_messages(bag: Path) -> tuple[list, int]:
    """([(topic, decoded message)], the file's message count) read with mcap + mcap-ros2-support."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    files = sorted(bag.glob("*.mcap"))
    assert files, f"no .mcap in {bag}"
    got, total = [], 0
    for f in files:
        with open(f, "rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            total += reader.get_summary().statistics.message_count
            got += [(ch.topic, msg) for _, ch, _, msg in reader.iter_decoded_messages()]
    return got, total


def test_world_bag_decodes_with_mcap_and_every_frame_reaches_world(world_bag):
    msgs, total = mcap_messages(world_bag)
    assert total > 0 and len(msgs) == total  # every message decoded
    by_topic: dict[str, list] = {}
    for topic, m in msgs:
        by_topic.setdefault(topic, []).append(m)
    n = len(by_topic["/joint_states"])
    assert n == 8
    cams = [t.split("/")[1] for t in by_topic if t.endswith("/color/image_raw")]
    assert len(cams) == 3
    for c in cams:  # the depth camera_info beside the colour one, equal to it
        depth_info, color_info = by_topic[f"/{c}/aligned_depth_to_color/camera_info"], by_topic[f"/{c}/color/camera_info"]
        assert len(depth_info) == len(color_info) == n
        assert list(depth_info[0].k) == list(color_info[0].k)
        assert depth_info[0].header.frame_id == by_topic[f"/{c}/aligned_depth_to_color/image_raw"][0].header.frame_id
    assert len(by_topic["/tf"]) == n and len(by_topic["/robot_description"]) == 1

    parents = tf_parents(by_topic["/tf_static"] + by_topic["/tf"])
    used = set().union(*(frame_ids(m) for _, m in msgs))
    assert {"world", "panda_link0", "panda_hand", "cam_wrist_color_optical_frame"} <= used
    lost = sorted(f for f in used if not reaches(f, parents))
    assert not lost, f"frames with no TF path to world: {lost}"
    # the robot's links are those of its URDF, posed as the recorded joint states say
    from soma_ros.core.robot_frames import RobotFrames

    urdf = by_topic["/robot_description"][0].data
    assert "<robot" in urdf
    frames = RobotFrames(Path(__file__).resolve().parents[2] / "soma_ros/resources/robots/franka_panda/panda.urdf")
    assert set(frames.links) <= set(parents) | {"panda_link0"}
    js = by_topic["/joint_states"][-1]
    want = frames.link_poses(list(js.name), np.asarray(js.position))["panda_hand"][0]
    tf_last = {t.child_frame_id: t for t in by_topic["/tf"][-1].transforms}
    T = np.eye(4)
    frame = "panda_hand"
    while frame != "panda_link0":
        t = tf_last[frame]
        T = _tf_matrix(t.transform) @ T
        frame = t.header.frame_id
    np.testing.assert_allclose(T, want, atol=1e-6)


def _tf_matrix(tr) -> np.ndarray:
    from soma_ros.data.bags import tf_to_matrix

    return tf_to_matrix(tr)


def test_a_world_bag_still_trains_the_same_cameras(world_bag):
    """The bag reader places the wrist camera on its robot link, whose pose FK gives, although
    the bag's /tf also carries the link tree up to the world: mount link panda_hand."""
    from soma_ros.core.robot import RobotModel
    from soma_ros.data.bags import camera_mount, read_episode

    ep = read_episode(world_bag)
    links = RobotModel.from_config("panda").link_names
    frame, _ = camera_mount(ep, "cam_wrist", robot_links=links)
    assert frame == "panda_hand"
    assert camera_mount(ep, "cam_front", robot_links=links)[0] == "world"


# --------------------------------------------------------------------------- live node
def test_node_publishes_one_tf_tree_a_latched_robot_description_and_nan_depth(ros_env, ros_context, untrained_run):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String
    from tf2_msgs.msg import TFMessage

    from benchmarks.bench_live import LiveProbe, Poser
    from soma_ros.live import load_live

    live = load_live(str(untrained_run[0]), str(untrained_run[1]))
    poser = Poser(live.robot, live.base_to_sim.matrix(), live.required_joints, live.bundle.gravity)
    hover = poser.solve((0.5, 0.02, 0.75 + 0.25))
    probe = LiveProbe(ros_context, live.required_joints, cameras=("cam_front", "cam_wrist"), depth=True, info=True,
                      tf_static=True)
    tf_msgs = []
    probe.node.create_subscription(TFMessage, "/tf", tf_msgs.append, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    node = RosProcess("soma_ros.nodes.sim_node", sim_node_args(*untrained_run), ros_env, name="sim_node_tf")
    try:
        keys = [("image", "cam_front"), ("image", "cam_wrist"), ("depth", "cam_front"), ("depth", "cam_wrist"),
                ("info", "cam_front"), ("splats",), ("tf_static",), ("status",)]
        ok = probe.hold(hover, lambda: (all(probe.count.get(k, 0) for k in keys) and len(tf_msgs) > 2)
                        or not node.alive(), START_TIMEOUT)
        assert ok and node.alive(), (probe.count, node.output()[-3000:])

        # one tree: every frame on the node's topics reaches world through /tf_static + /tf
        parents = tf_parents([probe.last("tf_static")] + tf_msgs)
        used = set()
        for key in keys:
            used |= frame_ids(probe.last(*key))
        assert {"soma_sim", "soma_sim/cam_front_optical", "soma_sim/cam_wrist_optical"} <= used
        lost = sorted(f for f in used if not reaches(f, parents))
        assert not lost, f"frames with no TF path to world: {lost}"
        # the wrist camera hangs off the robot's hand, the hand off the base, the base off world
        chain, f = [], "soma_sim/cam_wrist_optical"
        while f != "world":
            f = parents[f]
            chain.append(f)
        assert chain[0] == "panda_hand" and chain[-2:] == [live.robot.base_link, "world"]
        assert parents["soma_sim/cam_front_optical"] == "world" and parents["soma_sim"] == "world"
        assert set(live.robot.link_names) <= set(parents) | {live.robot.base_link}

        # the TF tree places the wrist camera where the node rendered it from
        from soma_ros.data.bags import tf_to_matrix

        edges = {t.child_frame_id: t for m in [probe.last("tf_static")] + tf_msgs[-1:] for t in m.transforms}
        T, f = np.eye(4), "soma_sim/cam_wrist_optical"
        while f != "world":
            T = tf_to_matrix(edges[f].transform) @ T
            f = edges[f].header.frame_id
        wrist = live.cameras[[c.name for c in live.cameras].index("cam_wrist")]
        want = live.link_pose_sim(hover, wrist.mount_link) @ wrist.link_to_cam
        np.testing.assert_allclose(T, want, atol=1e-5)

        # depth: NaN where nothing is drawn, never 0; depth_image_proc makes no point at the origin
        for cam in ("cam_front", "cam_wrist"):
            dm, info = probe.last("depth", cam), probe.last("info", "cam_front")
            d = np.frombuffer(bytes(dm.data), np.float32).reshape(dm.height, dm.width)
            assert np.isnan(d).any() and np.isfinite(d).any() and not (d == 0).any(), cam
            pts = depth_image_proc_points(d, np.array(info.k).reshape(3, 3))
            assert np.linalg.norm(pts, axis=1).min() > 0.05, cam

        # /robot_description: latched -- a subscriber created now still gets it
        got = []
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        probe.node.create_subscription(String, "/robot_description", got.append, latched)
        assert probe.spin_until(lambda: bool(got), 20.0), "no latched /robot_description"
        import xml.etree.ElementTree as ET

        meshes = [m.get("filename") for m in ET.fromstring(got[0].data).iter("mesh")]
        assert meshes and all(urlparse(m).scheme == "file" and Path(urlparse(m).path).is_file() for m in meshes)
        assert node.alive()
    finally:
        node.stop()
        probe.close()
