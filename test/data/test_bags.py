"""Bag ingestion: a reference-world bag reads into consistent training tensors, and broken
bags (a missing camera topic, a wrong image encoding, an empty /joint_states) fail with a
one-line error that names the problem -- from the Python API and from `soma train`.

Broken bags are made by copying the messages of a good bag with rosbags and dropping or
altering topics.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def good_dataset(tmp_path_factory) -> Path:
    from soma_ros.world import generate_dataset, load_world_config

    out = tmp_path_factory.mktemp("bags") / "rope"
    generate_dataset(load_world_config(), "rope", "tiny", out, episodes=1, seed=3, task="lift", frames=12,
                     progress=False)
    return out


@pytest.fixture(scope="module")
def robot():
    from soma_ros.core.robot import RobotModel

    return RobotModel.from_config("panda", dtype=torch.float64)


def copy_bag(src: Path, dst: Path, drop: tuple[str, ...] = (), empty: tuple[str, ...] = (), alter=None,
             storage: str = "sqlite3") -> Path:
    """Copy every message of bag `src` into a new bag `dst`; topics in `drop` are left out, topics in
    `empty` keep their connection but no message; `alter(topic, msg) -> msg` may change messages."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    from soma_ros.bagtypes import typestore

    ts = typestore()
    plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}[storage]
    with AnyReader([src], default_typestore=ts) as r, Writer(dst, version=9, storage_plugin=plugin) as w:
        conns = {}
        for c in r.connections:
            if c.topic in drop:
                continue
            conns[c.id] = w.add_connection(c.topic, c.msgtype, typestore=ts)
        for c, stamp, raw in r.messages():
            if c.id not in conns or c.topic in empty:
                continue
            if alter is not None:
                msg = alter(c.topic, r.deserialize(raw, c.msgtype))
                raw = ts.serialize_cdr(msg, c.msgtype)
            w.write(conns[c.id], stamp, raw)
    return dst


def one_line_error(fn) -> str:
    from soma_ros.data.bags import BagError

    with pytest.raises(BagError) as exc:
        fn()
    msg = str(exc.value)
    assert "\n" not in msg and len(msg) < 300, msg
    return msg


def test_prepare_episode_shapes_frames_and_actions(good_dataset, robot):
    from soma_ros.core.calibration import Sim3
    from soma_ros.data.bags import FORBIDDEN_TOPICS
    from soma_ros.data.dataset import load_dataset, prepare_episode

    refs = load_dataset(good_dataset)
    assert [r.name for r in refs] == ["rope_000"] and refs[0].task == "lift"
    ep = prepare_episode(refs[0].bag, robot)
    T, C, H, W = ep.num_frames, ep.num_cameras, ep.height, ep.width
    assert (T, C, H, W) == (12, 3, 120, 160)
    assert ep.camera_names == ["cam_front", "cam_side", "cam_wrist"]
    assert ep.rgb.dtype == torch.float32 and ep.rgb.shape == (T, C, H, W, 3) and 0 <= ep.rgb.min() and ep.rgb.max() <= 1
    assert torch.equal(ep.loss_mask, ep.object_mask & ~ep.robot_mask)
    assert abs(ep.dt - 1 / 30) < 1e-6
    # R2S: the wrist camera gives base -> sim; on a calibrated rig that is tf world <- base
    # (the reference world puts the Panda base on the table top at z = 0.75)
    M = ep.base_to_sim.matrix()
    assert np.allclose(M, Sim3(1.0, np.eye(3), np.array([0.0, 0.0, 0.75])).matrix(), atol=1e-6)
    # fixed cameras are fixed; the wrist camera moves with FK
    fixed = ep.camera_index("cam_front")
    wrist = ep.camera_index("cam_wrist")
    assert torch.allclose(ep.cam_to_world[0, fixed], ep.cam_to_world[-1, fixed])
    assert (ep.cam_to_world[0, wrist, :3, 3] - ep.cam_to_world[-1, wrist, :3, 3]).norm() > 0.01
    assert ep.mounted_camera() == "cam_wrist" and ep.mounts["cam_wrist"][0] == "panda_hand"
    # actions: 30 control points in the sim frame near the end effector, gripper in [0, 1]
    a = ep.action(0)
    assert a.control_points.shape == (30, 3) and 0.0 <= float(a.gripper) <= 1.0
    assert (ep.control_points[0].double().mean(0) - ep.ee_pose[0, :3, 3]).norm() < 0.15
    # fused object points lie on the table top (z ~ 0.75 .. 0.77) in the sim frame
    pts, cols = ep.object_points([0])
    assert len(pts) > 100 and cols.shape == pts.shape
    assert 0.745 < float(pts[:, 2].min()) and float(pts[:, 2].max()) < 0.78
    # CameraInfo's pixel centres (integers) are converted to the renderer's (+0.5): every
    # camera's table pixels back-project onto the table top (z = 0.75); read as-is they land
    # 2.8-2.9 mm below it from the fixed cameras
    from soma_ros.data.dataset import backproject

    for c, name in enumerate(ep.camera_names):
        table = ~ep.object_mask[0, c] & ~ep.robot_mask[0, c] & (ep.depth[0, c] > 0)
        p, _ = backproject(ep.depth[0, c], ep.K[c].double(), ep.cam_to_world[0, c].double(), table)
        z = p[:, 2][(p[:, 2] - 0.75).abs() < 0.05]
        assert len(z) > 1000 and abs(float(z.median()) - 0.75) < 5e-4, (name, float(z.median()))
    cams = ep.cameras(0)
    assert len(cams) == 3 and (cams.width, cams.height) == (160, 120)
    uv, z = cams.select([fixed]).project(pts)
    assert (z > 0).all()
    # downscaled training resolution
    from soma_ros.data.config import DataConfig

    half = prepare_episode(refs[0].bag, robot, DataConfig(resolution_scale=0.5))
    assert (half.width, half.height) == (80, 60) and torch.allclose(half.K[:, :2], ep.K[:, :2] * 0.5)
    assert "/world/object_points" in FORBIDDEN_TOPICS


def test_mcap_bag_reads_the_same(good_dataset, robot, tmp_path):
    from soma_ros.data.dataset import prepare_episode

    src = good_dataset / "rope_000"
    mc = copy_bag(src, tmp_path / "mcap_bag", storage="mcap")
    a = prepare_episode(src, robot)
    b = prepare_episode(mc, robot)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth) and torch.equal(a.control_points, b.control_points)


def test_missing_camera_topic_names_it(good_dataset, robot, tmp_path):
    from soma_ros.data.dataset import prepare_episode

    bad = copy_bag(good_dataset / "rope_000", tmp_path / "no_side_color", drop=("/cam_side/color/image_raw",))
    msg = one_line_error(lambda: prepare_episode(bad, robot))
    assert "missing topic /cam_side/color/image_raw" in msg
    bad2 = copy_bag(good_dataset / "rope_000", tmp_path / "no_wrist_depth",
                    drop=("/cam_wrist/aligned_depth_to_color/image_raw",))
    assert "/cam_wrist/aligned_depth_to_color/image_raw" in one_line_error(lambda: prepare_episode(bad2, robot))


def test_wrong_image_encoding_names_it(good_dataset, robot, tmp_path):
    from soma_ros.data.dataset import prepare_episode

    def yuv(topic, msg):
        if topic == "/cam_front/color/image_raw":
            msg.encoding = "yuv422"
        return msg

    bad = copy_bag(good_dataset / "rope_000", tmp_path / "yuv", alter=yuv)
    msg = one_line_error(lambda: prepare_episode(bad, robot))
    assert "/cam_front/color/image_raw" in msg and "yuv422" in msg


def test_empty_joint_states_names_it(good_dataset, robot, tmp_path):
    from soma_ros.data.dataset import prepare_episode

    bad = copy_bag(good_dataset / "rope_000", tmp_path / "empty_js", empty=("/joint_states",))
    assert "/joint_states is empty" in one_line_error(lambda: prepare_episode(bad, robot))
    gone = copy_bag(good_dataset / "rope_000", tmp_path / "no_js", drop=("/joint_states",))
    assert "missing topic /joint_states" in one_line_error(lambda: prepare_episode(gone, robot))


def test_joint_efforts_are_read_when_every_message_has_them(good_dataset, robot, tmp_path):
    """The world records efforts (the arm's external torques, the gripper's force): they are read
    per joint name at the frame stamps and give the wrist force; a bag whose /joint_states carry
    none (a rig without torque sensing), or only some messages with them, gives None."""
    from soma_ros.data.bags import read_episode
    from soma_ros.data.dataset import prepare_episode

    src = good_dataset / "rope_000"
    ep = read_episode(src)
    assert ep.joint_efforts is not None and ep.joint_efforts.shape == ep.joint_positions.shape
    assert np.all(np.isfinite(ep.joint_efforts)) and np.abs(ep.joint_efforts).max() > 0
    full = prepare_episode(src, robot)
    assert full.wrist_force is not None and full.wrist_force.shape == (full.num_frames, 3)

    def reorder(topic, msg):  # another joint order: the names decide, not the positions
        if topic == "/joint_states":
            for f in ("name", "position", "velocity", "effort"):
                setattr(msg, f, getattr(msg, f)[::-1].copy() if f != "name" else list(msg.name)[::-1])
        return msg

    rev = read_episode(copy_bag(src, tmp_path / "rev", alter=reorder))
    assert rev.joint_names == ep.joint_names[::-1]
    np.testing.assert_array_equal(rev.joint_efforts[:, ::-1], ep.joint_efforts)

    def no_effort(topic, msg):
        if topic == "/joint_states":
            msg.effort = np.zeros(0)
        return msg

    none = copy_bag(src, tmp_path / "none", alter=no_effort)
    assert read_episode(none).joint_efforts is None and prepare_episode(none, robot).wrist_force is None
    count = [0]

    def some(topic, msg):
        if topic == "/joint_states":
            count[0] += 1
            if count[0] % 2:
                msg.effort = np.zeros(0)
        return msg

    assert read_episode(copy_bag(src, tmp_path / "some", alter=some)).joint_efforts is None


def test_soma_train_reports_a_broken_bag_in_one_line(good_dataset, tmp_path):
    """The CLI turns the BagError into `soma train: error: ...` on one line, exit code 1."""

    def yuv(topic, msg):
        if topic == "/cam_wrist/color/image_raw":
            msg.encoding = "yuv422"
        return msg

    data = tmp_path / "bad_dataset"
    data.mkdir()
    copy_bag(good_dataset / "rope_000", data / "rope_000", alter=yuv)
    man = json.loads((good_dataset / "manifest.json").read_text())
    (data / "manifest.json").write_text(json.dumps(man))
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    p = subprocess.run([sys.executable, "-m", "soma_ros.cli", "train", "--data", str(data), "--config", "tiny",
                        "--out", str(tmp_path / "run"), "--quiet"], capture_output=True, text=True, env=env,
                       timeout=300)
    assert p.returncode == 2, p.stderr[-2000:]
    lines = [ln for ln in p.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith("soma train: error:") and "/cam_wrist/color/image_raw" in lines[0] and "yuv422" in lines[0]
