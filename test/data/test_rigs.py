"""Recordings from other rigs: datasets without manifests, renamed / nested / compressed cameras,
bags without masks (masks derived from geometry), another robot, and bad bags listed and skipped.

Real-rig forms are made from a reference-world bag with ``tools/rig_bags.py`` (rosbags).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))

from rig_bags import RigForm, corrupt_bag, rewrite_bag, truncate_bag, write_manifest  # noqa: E402

RENAME = {"cam_front": "front", "cam_side": "side", "cam_wrist": "wrist"}


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    from soma_ros.world import generate_dataset, load_world_config

    out = tmp_path_factory.mktemp("rigs") / "rope"
    generate_dataset(load_world_config(), "rope", "tiny", out, episodes=1, seed=5, task="lift", frames=10,
                     progress=False)
    return out / "rope_000"


@pytest.fixture(scope="module")
def robot():
    from soma_ros.core.robot import RobotModel

    return RobotModel.from_config("panda", dtype=torch.float64)


@pytest.fixture(scope="module")
def reference(world, robot):
    from soma_ros.data.bags import read_episode
    from soma_ros.data.dataset import prepare_episode

    return read_episode(world, require_masks=True), prepare_episode(world, robot)


def _one_line(msg: str) -> str:
    assert "\n" not in msg and len(msg) < 400, msg
    return msg


# --------------------------------------------------------------------------- dataset forms
def test_folder_without_manifest_one_bag_and_several_bags(world, tmp_path):
    from soma_ros.data.sources import ANY_SPLIT, default_split, load_dataset, write_split

    d = tmp_path / "recordings"
    for n in ("b_run", "a_run", "nested/c_run", "nested/d_run"):
        shutil.copytree(world, d / n)
    refs = load_dataset(d)
    assert [r.name for r in refs] == ["a_run", "b_run", "nested/c_run", "nested/d_run"]  # sorted
    split = default_split([r.name for r in refs], 0.3, 0)
    assert [r.split for r in refs] == [split[r.name] for r in refs]
    assert sorted(split.values()).count("test") == 1  # round(0.3 * 4) = 1
    assert split == default_split(list(reversed([r.name for r in refs])), 0.3, 0)  # order-independent
    assert {r.name for r in load_dataset(d, "test")} == {n for n, s in split.items() if s == "test"}
    out = write_split(tmp_path / "run", d, refs, 0.3, 0)
    doc = json.loads(out.read_text())
    assert [e["split"] for e in doc["episodes"]] == [r.split for r in refs] and doc["seed"] == 0
    one = load_dataset(d / "a_run")
    assert len(one) == 1 and one[0].split == ANY_SPLIT and load_dataset(d / "a_run", "test") == one
    two = load_dataset([d / "a_run", d / "nested/c_run"], "train")
    assert [r.name for r in two] == ["a_run", "c_run"]


def test_both_manifest_forms_and_a_wrong_one(world, tmp_path):
    from soma_ros.data.sources import load_dataset

    d = tmp_path / "ds"
    for n in ("front_0", "front_1", "front_2"):
        shutil.copytree(world, d / n)
    write_manifest(d, ["front_0", "front_1", "front_2"], "plain")
    assert [(r.name, r.split) for r in load_dataset(d)] == [("front_0", "train"), ("front_1", "train"), ("front_2", "test")]
    write_manifest(d, ["front_0", "front_1", "front_2"], "entries")
    assert [r.split for r in load_dataset(d)] == ["train", "train", "test"]
    (d / "manifest.json").write_text(json.dumps({"episodes": ["front_0", "front_1"]}))  # names, no split
    assert {r.split for r in load_dataset(d)} == {"train", "test"}
    for bad in ({"episodes": [{"bag": "front_0"}]}, {"runs": ["front_0"]}, {"episodes": ["front_0"], "split": ["x"]}):
        (d / "manifest.json").write_text(json.dumps(bad))
        with pytest.raises(ValueError) as exc:
            load_dataset(d)
        msg = _one_line(str(exc.value))
        assert "manifest.json" in msg and '{"episodes": [names], "split"' in msg
    (d / "manifest.json").write_text(json.dumps({"episodes": ["front_0"], "split": {"test": ["nope"]}}))
    with pytest.raises(ValueError, match="split 'test' names 'nope'"):
        load_dataset(d)


# --------------------------------------------------------------------------- topic discovery
def test_discovery_of_flat_and_nested_layouts():
    from soma_ros.data.bags import discover_cameras

    img, info, comp = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/CompressedImage"
    topics = {"/joint_states": "sensor_msgs/msg/JointState",
              "/front/color/image_raw": img, "/front/color/camera_info": info,
              "/front/aligned_depth_to_color/image_raw": img,
              "/rig/wrist/color/image_raw/compressed": comp, "/rig/wrist/aligned_depth_to_color/camera_info": info,
              "/rig/wrist/aligned_depth_to_color/image_raw": img,
              "/a/cam/color/image_raw": img, "/b/cam/color/image_raw": img}
    cams = discover_cameras(topics)
    assert sorted(cams) == ["a_cam", "b_cam", "front", "wrist"]
    assert cams["wrist"].namespace == "rig/wrist" and cams["wrist"].color_compressed
    assert cams["wrist"].camera_info == "/rig/wrist/aligned_depth_to_color/camera_info"
    assert cams["front"].camera_info == "/front/color/camera_info" and not cams["front"].problems()
    assert any("camera_info" in p for p in cams["a_cam"].problems())


def test_renamed_nested_compressed_camera_bag_reads_like_the_original(world, reference, robot, tmp_path):
    """Renamed cameras (and frames), a nested namespace, JPEG colour, camera_info only from the
    aligned depth, mcap storage, no masks: same depth, poses and actions; colour within JPEG error;
    masks derived from geometry close to the world's own."""
    from soma_ros.data.dataset import prepare_episode
    from soma_ros.data.masks import mask_iou

    form = RigForm(strip_masks=True, rename=RENAME, compressed="jpeg", namespace="rig", info_from_depth=True,
                   storage="mcap")
    bag = rewrite_bag(world, tmp_path / "real", form)
    truth, ref = reference
    ep = prepare_episode(bag, robot)
    assert ep.camera_names == ["front", "side", "wrist"]
    assert ep.mask_source == {"front": "derived", "side": "derived", "wrist": "derived"}
    for new, old in (("front", "cam_front"), ("side", "cam_side"), ("wrist", "cam_wrist")):
        i, j = ep.camera_index(new), ref.camera_index(old)
        assert torch.equal(ep.depth[:, i], ref.depth[:, j])
        assert torch.allclose(ep.cam_to_world[:, i], ref.cam_to_world[:, j], atol=1e-9)
        assert float((ep.rgb[:, i] - ref.rgb[:, j]).abs().mean()) < 4 / 255
        o = [mask_iou(ep.object_mask[t, i].numpy(), truth.cameras[old].object_mask[t]) for t in range(ep.num_frames)]
        r = [mask_iou(ep.robot_mask[t, i].numpy(), truth.cameras[old].robot_mask[t]) for t in range(ep.num_frames)]
        assert np.median(o) >= 0.8 and np.median(r) >= 0.9, (new, np.median(o), np.median(r))
    assert ep.mounted_camera() == "wrist" and ep.mounts["wrist"][0] == "panda_hand"
    assert torch.equal(ep.control_points, ref.control_points)


def test_bgr8_and_32fc1_depth_and_tf_extrinsics(world, reference, robot, tmp_path):
    """bgr8 colour and 32FC1 depth in metres read the same; a fixed camera whose extrinsics arrive
    on /tf instead of /tf_static is placed the same."""
    from soma_ros.data.dataset import prepare_episode

    moved = []

    def front_on_tf(topic, msg):
        if topic == "/tf_static":
            keep = [tr for tr in msg.transforms if not tr.child_frame_id.startswith("cam_front")]
            moved.extend(tr for tr in msg.transforms if tr.child_frame_id.startswith("cam_front"))
            msg.transforms = keep
        return msg

    bag = rewrite_bag(world, tmp_path / "bgr", RigForm(bgr=True, depth_32f=True), alter=front_on_tf)
    assert moved, "the reference bag has no cam_front transform in /tf_static"
    # write the moved transforms on /tf (a driver that publishes extrinsics dynamically)
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Writer

    from soma_ros.bagtypes import typestore

    ts = typestore()
    dst = tmp_path / "bgr_tf"
    with AnyReader([bag], default_typestore=ts) as r, Writer(dst, version=9) as w:
        conns = {c.id: w.add_connection(c.topic, c.msgtype, typestore=ts) for c in r.connections}
        tf = next((conns[c.id] for c in r.connections if c.topic == "/tf"), None)  # the robot's links, if recorded
        tf = tf or w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        TF = ts.types["tf2_msgs/msg/TFMessage"]
        first = True
        for c, stamp, raw in r.messages():
            if first:
                w.write(tf, stamp, ts.serialize_cdr(TF(transforms=moved), "tf2_msgs/msg/TFMessage"))
                first = False
            w.write(conns[c.id], stamp, raw)
    _, ref = reference
    ep = prepare_episode(dst, robot)
    assert torch.equal(ep.rgb, ref.rgb)
    assert torch.allclose(ep.depth, ref.depth, atol=1e-6)
    i = ep.camera_index("cam_front")
    assert torch.allclose(ep.cam_to_world[:, i], ref.cam_to_world[:, i], atol=1e-9)


def test_a_bag_retargeted_to_another_robot_reads_with_that_robot_like_the_original(world, reference, tmp_path):
    """``tools/retarget_robot.py``: the same episode as the ARX X5 (6 joints, the gripper an
    external value in metres, no finger links) would have done it, read with ``robot=arx5``:
    its control points follow the Panda's (centroids apart by the two jaws' shapes: 2.0 against
    1.8 cm long, tips aligned, so 1 mm), the opening in metres and the wrist camera's pose are the
    recorded ones, images and depth unchanged, and the bag names only the ARX's joints."""
    from rosbags.highlevel import AnyReader

    from retarget_robot import base_pose, retarget_bag
    from soma_ros.bagtypes import typestore
    from soma_ros.core.robot import RobotModel
    from soma_ros.data.dataset import prepare_episode

    _, ref = reference
    panda = RobotModel.from_config("panda", dtype=torch.float64)
    arx = RobotModel.from_config("arx5", dtype=torch.float64)
    info = retarget_bag(world, tmp_path / "arx", panda, arx, base_pose((0.15, 0.0, 0.85, 0.0)))
    assert info["frames"] == ref.num_frames and info["worst_mm"] < 1.0 and info["worst_deg"] < 0.5, info
    with AnyReader([tmp_path / "arx"], default_typestore=typestore()) as r:
        c = next(c for c in r.connections if c.topic == "/joint_states")
        names = {n for _, _, raw in r.messages([c]) for n in r.deserialize(raw, c.msgtype).name}
        assert not any(c.topic == "/tf" for c in r.connections)
    assert names == set(arx.arm_joint_names) | {"gripper"}
    ep = prepare_episode(tmp_path / "arx", arx)
    assert torch.equal(ep.rgb, ref.rgb) and torch.equal(ep.depth, ref.depth)
    d = (ep.control_points.mean(-2) - ref.control_points.mean(-2)).norm(dim=-1)
    assert 0.9e-3 < float(d.min()) and float(d.max()) < 1.1e-3, (float(d.min()), float(d.max()))
    assert torch.allclose(ep.gripper_opening.double(), ref.gripper_opening.double(), atol=1e-9)
    assert ep.mounts["cam_wrist"][0] == "eef_link"
    i, j = ep.camera_index("cam_wrist"), ref.camera_index("cam_wrist")
    A, B = ep.cam_to_world[:, i].double(), ref.cam_to_world[:, j].double()
    assert float((A[:, :3, 3] - B[:, :3, 3]).norm(dim=-1).max()) < 1e-3
    cos = ((A[:, :3, :3].transpose(1, 2) @ B[:, :3, :3]).diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2
    assert float(torch.rad2deg(torch.arccos(cos.clamp(-1, 1))).max()) < 0.5


# --------------------------------------------------------------------------- masks
def test_box_rasterizes_to_its_projection():
    """A unit cube 2 m in front of the camera covers the pixels whose centres fall inside its
    projected front face, at depth 1.5 m."""
    import trimesh

    from soma_ros.core.robot_meshes import render_depth

    m = trimesh.creation.box(extents=[1.0, 1.0, 1.0])
    K = np.array([[100.0, 0, 49.5], [0, 100.0, 39.5], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, 3] = [0, 0, 2.0]
    d = render_depth({"box": (np.asarray(m.vertices), np.asarray(m.faces))}, {"box": pose}, K, np.eye(4), 100, 80)
    hit = np.isfinite(d)
    u = np.arange(100) - 49.5
    v = np.arange(80) - 39.5
    inside = (np.abs(u)[None, :] <= 100 * 0.5 / 1.5) & (np.abs(v)[:, None] <= 100 * 0.5 / 1.5)
    assert inside.sum() == 66 * 66 and np.array_equal(hit, inside)
    assert np.allclose(d[hit & inside], 1.5, atol=1e-9)
    assert hit[40, 50] and not hit[0, 0]


def test_user_mask_folder_takes_precedence(world, robot, tmp_path):
    import cv2

    from soma_ros.data.config import DataConfig
    from soma_ros.data.dataset import prepare_episode

    bag = rewrite_bag(world, tmp_path / "nomask", RigForm(strip_masks=True))
    folder = tmp_path / "masks"
    for t in range(10):
        m = np.zeros((120, 160), np.uint8)
        m[10:20, 30:50] = 255
        (folder / "nomask" / "cam_side").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(folder / "nomask" / "cam_side" / f"object_{t:06d}.png"), m)
    cfg = DataConfig()
    cfg.masks.folder = str(folder)
    ep = prepare_episode(bag, robot, cfg, mask_cache=tmp_path / "cache")
    assert ep.mask_source == {"cam_front": "derived", "cam_side": "folder", "cam_wrist": "derived"}
    i = ep.camera_index("cam_side")
    assert int(ep.object_mask[:, i].sum()) == 10 * 200
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 1  # derived masks cached beside the run
    again = prepare_episode(bag, robot, cfg, mask_cache=tmp_path / "cache")
    assert torch.equal(again.object_mask, ep.object_mask)
    assert sorted(p.name for p in bag.iterdir()) == sorted(p.name for p in (tmp_path / "nomask").iterdir())


def test_a_urdf_whose_meshes_are_missing_names_them_and_the_remedy_when_masks_must_be_derived(world, tmp_path):
    """Robot pixels are derived from the URDF's meshes; a URDF copied without its mesh files (a
    robot description whose meshes were not installed) gets one line that names the missing
    file and says what to do, not a traceback and not masks from a cruder stand-in."""
    from soma_ros.core.robot import RobotModel
    from soma_ros.data.dataset import prepare_episode

    src = ROOT / "soma_ros" / "resources" / "robots" / "franka_panda" / "panda.urdf"
    shutil.copy(src, tmp_path / "panda.urdf")
    yaml = (ROOT / "config" / "robots" / "panda.yaml").read_text()
    (tmp_path / "panda.yaml").write_text(yaml.replace("urdf: franka_panda/panda.urdf", f"urdf: {tmp_path / 'panda.urdf'}"))
    robot = RobotModel.from_config(str(tmp_path / "panda.yaml"), dtype=torch.float64)
    bag = rewrite_bag(world, tmp_path / "nomask", RigForm(strip_masks=True))
    with pytest.raises(FileNotFoundError) as e:
        prepare_episode(bag, robot)
    msg = _one_line(str(e.value))
    assert "URDF mesh not found: package://meshes/collision/link0.obj" in msg and "data.masks.folder" in msg, msg
    prepare_episode(world, robot)  # with the bag's own masks the meshes are not needed


# --------------------------------------------------------------------------- bad input
def _bad_bags(world: Path, d: Path) -> dict[str, tuple[Path, str]]:
    """{class: (bag, expected message fragment)}."""
    def rename_joint(topic, msg):
        if topic == "/joint_states":
            msg.name = ["arm_" + n for n in msg.name]
        return msg

    def no_tf_for_side(topic, msg):
        if topic == "/tf_static":
            msg.transforms = [tr for tr in msg.transforms if not tr.child_frame_id.startswith("cam_side")]
        return msg

    def late_depth(topic, msg):
        if topic == "/cam_front/aligned_depth_to_color/image_raw":
            msg.header.stamp.nanosec = (msg.header.stamp.nanosec + 100_000_000) % 1_000_000_000
            if msg.header.stamp.nanosec < 100_000_000:
                msg.header.stamp.sec += 1
        return msg

    out = {
        "no joint states": (rewrite_bag(world, d / "no_js", drop=("/joint_states",)), "missing topic /joint_states"),
        "unknown joint names": (rewrite_bag(world, d / "joint_names", alter=rename_joint), "/joint_states"),
        "no TF path": (rewrite_bag(world, d / "no_tf", alter=no_tf_for_side), "/cam_side/color/camera_info"),
        "unsynchronised": (rewrite_bag(world, d / "late_depth", alter=late_depth),
                           "/cam_front/aligned_depth_to_color/image_raw: not synchronised"),
        "empty": (rewrite_bag(world, d / "empty", empty=True), "empty"),
        "truncated": (truncate_bag(rewrite_bag(world, d / "truncated"), 0.4), "unreadable bag"),
        "corrupt sqlite3": (corrupt_bag(rewrite_bag(world, d / "corrupt_db3"), 0.0), "unreadable bag"),
        "corrupt mcap": (corrupt_bag(rewrite_bag(world, d / "corrupt_mcap", RigForm(storage="mcap")), 0.0, 4096),
                         "unreadable bag"),
    }
    shutil.copytree(world, d / "good")
    return out


def test_every_bad_bag_class_is_named_and_skipped(world, robot, tmp_path):
    from soma_ros.data.bags import BagError
    from soma_ros.data.config import DataConfig
    from soma_ros.data.sources import load_dataset, probe_bag, usable_episodes

    d = tmp_path / "mixed"
    bad = _bad_bags(world, d)
    refs = load_dataset(d)
    assert len(refs) == len(bad) + 1
    for cls, (bag, frag) in bad.items():
        pr = probe_bag(bag, robot=robot)
        assert not pr.ok, cls
        msg = _one_line(pr.problems[0])
        assert msg.startswith(bag.name + ":") and frag in msg, (cls, msg)
    assert "arm_panda_joint1" in probe_bag(bad["unknown joint names"][0], robot=robot).problems[0]
    log: list[str] = []
    kept = usable_episodes(refs, robot, DataConfig(), log.append)
    assert [r.name for r in kept] == ["good"]
    assert len(log) == len(bad) and all(_one_line(x).startswith("skipping bag ") for x in log)
    with pytest.raises(BagError) as exc:
        usable_episodes(refs, robot, DataConfig(strict=True), log.append)
    assert "strict" in _one_line(str(exc.value))
    # the full reader names the same problems in one line
    from soma_ros.data.dataset import prepare_episode

    for cls in ("no joint states", "unknown joint names", "no TF path", "unsynchronised", "empty", "truncated",
                "corrupt sqlite3"):
        bag, frag = bad[cls]
        with pytest.raises(BagError) as exc:
            prepare_episode(bag, robot)
        assert bag.name in _one_line(str(exc.value)), (cls, str(exc.value))


def test_soma_dataset_check_lists_every_problem(world, tmp_path):
    d = tmp_path / "mixed"
    bad = _bad_bags(world, d)
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    p = subprocess.run([sys.executable, "-m", "soma_ros.cli", "dataset", "check", str(d), "--out", str(tmp_path / "sheets"),
                        "--frames", "2"], capture_output=True, text=True, env=env, cwd=ROOT, timeout=900)
    assert p.returncode == 1, p.stderr
    assert "Traceback" not in p.stderr
    lines = p.stderr.strip().splitlines()
    for cls, (bag, frag) in bad.items():
        assert any(line.startswith(bag.name + ":") and frag in line for line in lines), (cls, p.stderr)
    assert "1 of 9 bag(s) usable" in p.stdout
    assert "camera cam_front (/cam_front)" in p.stdout and "TF: world" in p.stdout
    assert (tmp_path / "sheets" / "masks_good.png").is_file()
    ok = subprocess.run([sys.executable, "-m", "soma_ros.cli", "dataset", "check", str(d / "good"), "--no-sheets"],
                        capture_output=True, text=True, env=env, cwd=ROOT, timeout=900)
    assert ok.returncode == 0, ok.stderr
