"""The MuJoCo reference world: bags like a real rig, consistent geometry, CLI.

Episodes are generated once per module (tiny preset) into tmp dirs.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

os.environ.setdefault("MUJOCO_GL", "egl")

from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from soma_ros.world import (  # noqa: E402
    CAMERA_NAMES,
    OBJECT_POINTS_TOPIC,
    generate_dataset,
    load_world_config,
    topics_for,
)
from soma_ros.world.transforms import quat_to_mat, rotation_angle_deg  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
W, H = 160, 120


def read_bag(bag: Path) -> dict[str, list]:
    """{topic: [(bag timestamp, msg)]} of a whole bag."""
    out: dict[str, list] = {}
    with AnyReader([bag], default_typestore=TYPESTORE) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        for c, t, raw in r.messages():
            out.setdefault(c.topic, []).append((t, r.deserialize(raw, c.msgtype)))
    out["__types__"] = types  # type: ignore[assignment]
    return out


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def tf_matrix(tr) -> np.ndarray:
    q = tr.rotation
    T = np.eye(4)
    T[:3, :3] = quat_to_mat([q.w, q.x, q.y, q.z])
    T[:3, 3] = [tr.translation.x, tr.translation.y, tr.translation.z]
    return T


@pytest.fixture(scope="module")
def cfg():
    return load_world_config()


@pytest.fixture(scope="module")
def worlds(cfg, tmp_path_factory):
    """One tiny dataset per object: rope (3 episodes, default tasks), cloth (fold), doll."""
    out = {}
    for obj, n, task in (("rope", 3, None), ("cloth", 1, "fold"), ("doll", 1, None)):
        d = tmp_path_factory.mktemp(f"world_{obj}")
        manifest = generate_dataset(cfg, obj, "tiny", d, episodes=n, seed=0, task=task, progress=False)
        ep = manifest["episodes"][0]
        out[obj] = {
            "dir": d,
            "manifest": manifest,
            "meta": json.loads((d / f"{ep['name']}.meta.json").read_text()),
            "bag": read_bag(d / ep["bag"]),
        }
    return out


# ----------------------------------------------------------------------------- layout


def test_manifest_and_files(worlds, cfg):
    w = worlds["rope"]
    m = json.loads((w["dir"] / "manifest.json").read_text())
    assert m == w["manifest"]
    for key in ("object", "preset", "seed", "effects", "storage", "episodes", "split_ratio"):
        assert key in m
    assert (m["object"], m["preset"], m["seed"], m["effects"], m["storage"]) == ("rope", "tiny", 0, [], "sqlite3")
    assert m["split_ratio"] == pytest.approx(0.7)
    assert [e["split"] for e in m["episodes"]].count("train") == 2  # round(0.7 * 3)
    assert [e["split"] for e in m["episodes"]].count("test") == 1
    for e in m["episodes"]:
        assert set(e) >= {"name", "bag", "split", "task", "frames", "seconds_to_generate"}
        assert e["task"] in cfg.tasks["rope"]
        assert e["frames"] == 40
        assert e["seconds_to_generate"] > 0
        assert (w["dir"] / e["bag"] / "metadata.yaml").is_file()
        assert (w["dir"] / f"{e['name']}.meta.json").is_file()
        png = w["dir"] / f"{e['name']}.contact.png"
        assert png.is_file() and png.stat().st_size > 10_000
    assert {e["task"] for e in m["episodes"]} == set(cfg.tasks["rope"])  # tasks take turns
    assert worlds["cloth"]["manifest"]["episodes"][0]["task"] == "fold"


def test_sidecar_holds_evaluation_facts(worlds, cfg):
    meta = worlds["doll"]["meta"]
    assert meta["evaluation_only"] is True
    assert meta["table"]["height_m"] == pytest.approx(cfg.table.height)
    assert meta["object_params"]["mass_kg"] == pytest.approx(cfg.objects["doll"].mass)
    assert meta["object_params"]["young_pa"] == pytest.approx(cfg.objects["doll"].young)
    assert meta["effects"] == {}
    assert meta["seed"] == 0 and meta["task"] in ("lift", "drag")
    assert len(meta["wrist_camera_world_poses"]) == meta["frames"]
    assert meta["grasp"]["held_vertices"], "the grasp held no vertex"


# ----------------------------------------------------------------------------- bag contents


@pytest.mark.parametrize("obj", ["rope", "cloth", "doll"])
def test_bag_topics_types_and_encodings(worlds, obj):
    bag = worlds[obj]["bag"]
    n = worlds[obj]["meta"]["frames"]
    expected = topics_for(CAMERA_NAMES)
    assert bag["__types__"] == expected
    assert len(bag["/tf_static"]) == len(bag["/robot_description"]) == 1  # latched, once
    for topic in expected:
        if topic not in ("/tf_static", "/robot_description"):
            assert len(bag[topic]) == n, topic
    js = bag["/joint_states"][0][1]
    assert js.name == [f"panda_joint{i}" for i in range(1, 8)] + ["panda_finger_joint1", "panda_finger_joint2"]
    assert len(js.position) == len(js.velocity) == len(js.effort) == 9  # effort: external torques + gripper force
    for cam in CAMERA_NAMES:
        fid = f"{cam}_color_optical_frame"
        for _, img in bag[f"/{cam}/color/image_raw"][:3]:
            assert (img.encoding, img.width, img.height, img.step) == ("rgb8", W, H, 3 * W)
            assert img.header.frame_id == fid and len(img.data) == W * H * 3
        for _, img in bag[f"/{cam}/aligned_depth_to_color/image_raw"][:3]:
            assert (img.encoding, img.step, img.is_bigendian) == ("16UC1", 2 * W, 0)
            depth = np.frombuffer(img.data.tobytes(), "<u2")
            assert depth.max() > 0 and depth.max() <= 3000  # millimetres, clipped at depth_max_m
        for topic in (f"/{cam}/object_mask", f"/{cam}/robot_mask"):
            for _, img in bag[topic]:
                assert (img.encoding, img.step) == ("mono8", W)
                assert set(np.unique(img.data)) <= {0, 255}
        info = bag[f"/{cam}/color/camera_info"][0][1]
        assert info.distortion_model == "plumb_bob" and info.header.frame_id == fid
        K = info.k.reshape(3, 3)
        assert K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] == 1
        assert np.allclose(info.p.reshape(3, 4)[:, :3], K)
    # The object is seen by every camera in most frames; the fingers are always in the wrist view.
    for cam in CAMERA_NAMES:
        seen = np.mean([img.data.max() > 0 for _, img in bag[f"/{cam}/object_mask"]])
        assert seen > 0.8, (cam, seen)
    assert all(img.data.max() > 0 for _, img in bag["/cam_wrist/robot_mask"])
    pc = bag[OBJECT_POINTS_TOPIC][0][1]
    assert pc.header.frame_id == "world"
    assert [(f.name, f.offset, f.datatype, f.count) for f in pc.fields] == [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)]
    assert pc.point_step == 12 and pc.width == worlds[obj]["meta"]["object_params"]["n_vertices"]


def test_tf_static_frames(worlds, cfg):
    tf = worlds["rope"]["bag"]["/tf_static"][0][1]
    pairs = {(t.header.frame_id, t.child_frame_id) for t in tf.transforms}
    assert pairs == {
        ("world", "panda_link0"),
        ("world", "cam_front_color_optical_frame"),
        ("world", "cam_side_color_optical_frame"),
        ("panda_hand", "cam_wrist_color_optical_frame"),
    }
    base = next(tf_matrix(t.transform) for t in tf.transforms if t.child_frame_id == "panda_link0")
    assert np.allclose(base[:3, 3], cfg.robot_base_xyz)
    # Optical convention: a fixed camera's z (forward) points at its look_at target.
    front = next(tf_matrix(t.transform) for t in tf.transforms if t.child_frame_id == "cam_front_color_optical_frame")
    fc = cfg.cameras.fixed["cam_front"]
    ray = np.asarray(fc.look_at) - np.asarray(fc.position)
    assert np.dot(front[:3, 2], ray / np.linalg.norm(ray)) > 0.9999
    assert front[2, 1] < 0  # image y (down) points downwards in the world


@pytest.mark.parametrize("obj", ["rope", "cloth", "doll"])
def test_timestamps_agree_across_topics(worlds, obj):
    bag = worlds[obj]["bag"]
    ref = [stamp_ns(m) for _, m in bag["/joint_states"]]
    assert np.allclose(np.diff(ref), 1e9 / 30.0, atol=1)
    for topic, items in bag.items():
        if topic in ("__types__",):
            continue
        if topic == "/robot_description":  # no header: the bag time only
            assert [t for t, _ in items] == ref[:1]
            continue
        stamps = [stamp_ns(m.transforms[0]) if topic in ("/tf", "/tf_static") else stamp_ns(m) for _, m in items]
        want = ref if topic != "/tf_static" else ref[:1]
        assert stamps == want, topic
        assert [t for t, _ in items] == want, topic  # bag time == header stamp


# ----------------------------------------------------------------------------- geometry


def _fk_wrist(bag, urdf: str) -> list[np.ndarray]:
    """world <- cam_wrist optical per frame: tf_static(world->base) FK(joint states) tf_static(hand->cam)."""
    import yourdfpy

    robot = yourdfpy.URDF.load(urdf, load_meshes=False, load_collision_meshes=False, build_collision_scene_graph=False)
    tf = {(t.header.frame_id, t.child_frame_id): tf_matrix(t.transform) for t in bag["/tf_static"][0][1].transforms}
    out = []
    for _, js in bag["/joint_states"]:
        q = dict(zip(js.name, js.position))
        robot.update_cfg({n: q[n] for n in robot.actuated_joint_names})
        T = tf[("world", "panda_link0")] @ robot.get_transform("panda_hand", "panda_link0")
        out.append(T @ tf[("panda_hand", "cam_wrist_color_optical_frame")])
    return out


@pytest.mark.parametrize("obj", ["rope", "cloth", "doll"])
def test_fk_of_joint_states_reproduces_wrist_camera(worlds, obj):
    w = worlds[obj]
    fk = _fk_wrist(w["bag"], w["meta"]["robot"]["urdf"])
    truth = w["meta"]["wrist_camera_world_poses"]
    pos_err = max(np.linalg.norm(T[:3, 3] - np.asarray(p[:3])) for T, p in zip(fk, truth))
    rot_err = max(rotation_angle_deg(T[:3, :3], quat_to_mat(p[3:])) for T, p in zip(fk, truth))
    print(f"{obj}: wrist camera FK error max {pos_err * 1e3:.2e} mm, {rot_err:.2e} deg")
    assert pos_err < 1e-3 and rot_err < 0.1
    # The arm really moved (the check is not vacuous).
    travel = max(np.linalg.norm(fk[0][:3, 3] - T[:3, 3]) for T in fk)
    assert travel > 0.05


@pytest.mark.parametrize("obj", ["rope", "cloth", "doll"])
def test_object_points_project_onto_object_mask(worlds, obj):
    """Ground-truth points, projected with the recorded K and extrinsics, land on object pixels."""
    w = worlds[obj]
    bag, meta = w["bag"], w["meta"]
    radius = meta["object_params"]["radius_m"]
    wrist = _fk_wrist(bag, meta["robot"]["urdf"])
    tf = {t.child_frame_id: tf_matrix(t.transform) for t in bag["/tf_static"][0][1].transforms}
    hits = total = 0
    for cam in CAMERA_NAMES:
        for k, (_, pc) in enumerate(bag[OBJECT_POINTS_TOPIC]):
            pts = np.frombuffer(pc.data.tobytes(), "<f4").reshape(-1, 3).astype(float)
            K = bag[f"/{cam}/color/camera_info"][k][1].k.reshape(3, 3)
            Twc = wrist[k] if cam == "cam_wrist" else tf[f"{cam}_color_optical_frame"]
            Tcw = np.linalg.inv(Twc)
            p = pts @ Tcw[:3, :3].T + Tcw[:3, 3]
            uv = p @ K.T
            u = np.round(uv[:, 0] / uv[:, 2]).astype(int)
            v = np.round(uv[:, 1] / uv[:, 2]).astype(int)
            mask = bag[f"/{cam}/object_mask"][k][1].data.reshape(H, W)
            depth = np.frombuffer(bag[f"/{cam}/aligned_depth_to_color/image_raw"][k][1].data.tobytes(), "<u2")
            depth = depth.reshape(H, W) / 1000.0
            inside = (p[:, 2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
            # Visible: the rendered surface at the pixel is the point's own surface (within its radius).
            dd = depth[v[inside], u[inside]] - p[inside, 2]
            vis = (dd > -radius - 0.002) & (dd < 0.002)
            hits += int((mask[v[inside], u[inside]][vis] > 0).sum())
            total += int(vis.sum())
    frac = hits / max(total, 1)
    print(f"{obj}: {total} visible points, {frac:.4f} on the object mask")
    assert total > 100
    assert frac >= 0.95


def test_depth_is_metric_on_the_table(worlds, cfg):
    """Back-projected depth of table pixels lies on the table plane (intrinsics + extrinsics + metric depth)."""
    bag = worlds["cloth"]["bag"]
    tf = {t.child_frame_id: tf_matrix(t.transform) for t in bag["/tf_static"][0][1].transforms}
    for cam in ("cam_front", "cam_side"):
        K = bag[f"/{cam}/color/camera_info"][0][1].k.reshape(3, 3)
        d = np.frombuffer(bag[f"/{cam}/aligned_depth_to_color/image_raw"][0][1].data.tobytes(), "<u2").reshape(H, W)
        free = (bag[f"/{cam}/object_mask"][0][1].data.reshape(H, W) == 0) & (bag[f"/{cam}/robot_mask"][0][1].data.reshape(H, W) == 0)
        vv, uu = np.mgrid[H // 2 : H - 2, W // 4 : 3 * W // 4]  # lower middle of the image: the table top
        sel = free[vv, uu] & (d[vv, uu] > 0)
        z = d[vv, uu][sel] / 1000.0
        rays = np.linalg.inv(K) @ np.stack([uu[sel], vv[sel], np.ones(sel.sum())])
        pw = tf[f"{cam}_color_optical_frame"] @ np.vstack([rays * z, np.ones(sel.sum())])
        err = np.abs(pw[2] - cfg.table.height)
        assert sel.sum() > 500
        assert np.median(err) < 0.002, (cam, np.median(err))


def test_same_seed_same_episode(worlds, cfg, tmp_path):
    m = generate_dataset(cfg, "rope", "tiny", tmp_path, episodes=1, seed=0, progress=False)
    again = read_bag(tmp_path / m["episodes"][0]["bag"])
    first = worlds["rope"]["bag"]
    for topic in ("/joint_states", OBJECT_POINTS_TOPIC, "/cam_front/color/image_raw"):
        a = [msg for _, msg in first[topic]]
        b = [msg for _, msg in again[topic]]
        for x, y in zip(a, b):
            if topic == "/joint_states":
                assert np.array_equal(x.position, y.position)
            else:
                assert np.array_equal(x.data, y.data)
    other = generate_dataset(cfg, "rope", "tiny", tmp_path / "s1", episodes=1, seed=1, progress=False, frames=8)
    p1 = read_bag(tmp_path / "s1" / other["episodes"][0]["bag"])[OBJECT_POINTS_TOPIC][0][1].data
    assert not np.array_equal(p1, first[OBJECT_POINTS_TOPIC][0][1].data)  # another seed, another placement


def test_workers_write_the_same_bags_and_manifest_in_order(cfg, tmp_path):
    one = generate_dataset(cfg, "rope", "tiny", tmp_path / "w1", episodes=3, seed=4, frames=8, progress=False)
    two = generate_dataset(cfg, "rope", "tiny", tmp_path / "w2", episodes=3, seed=4, frames=8, progress=False,
                           workers=2)
    on_disk = json.loads((tmp_path / "w2" / "manifest.json").read_text())
    for m in (one, two, on_disk):
        for e in m["episodes"]:
            e.pop("seconds_to_generate")
    assert [e["name"] for e in two["episodes"]] == ["rope_000", "rope_001", "rope_002"]
    assert one == two == on_disk
    for e in one["episodes"]:
        a, b = (next((tmp_path / w / e["bag"]).glob("*.db3")).read_bytes() for w in ("w1", "w2"))
        assert a == b, e["name"]
    with pytest.raises(ValueError, match="workers must be >= 1"):
        generate_dataset(cfg, "rope", "tiny", tmp_path / "w0", episodes=1, frames=8, progress=False, workers=0)


def test_mcap_storage(cfg, tmp_path):
    m = generate_dataset(cfg, "rope", "tiny", tmp_path, episodes=1, seed=2, storage="mcap", frames=8, progress=False)
    bag_dir = tmp_path / m["episodes"][0]["bag"]
    assert list(bag_dir.glob("*.mcap"))
    bag = read_bag(bag_dir)
    assert bag["__types__"] == topics_for(CAMERA_NAMES)
    assert len(bag["/joint_states"]) == 8 and m["storage"] == "mcap"


def test_an_exploded_object_rejects_the_episode_and_leaves_nothing(cfg, tmp_path):
    """A frame whose object has an element stretched beyond physics.max_element_stretch is a
    simulation that blew up (a rope that fell off the table in a strong wind once stretched 21x):
    generation stops with an error naming the frame, and no half-written bag is left. The limit is
    set just above 1 here so the first frame trips it."""
    from dataclasses import replace

    from soma_ros.world.simulate import element_edges, max_edge_stretch

    tet = np.array([[0, 1, 2, 3]])
    assert element_edges(tet).tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]
    assert element_edges(np.array([[0, 1], [1, 2], [2, 1]])).tolist() == [[0, 1], [1, 2]]
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]])
    assert max_edge_stretch(pts, np.array([[0, 1], [1, 2]]), np.array([1.0, 1.0])) == 2.0
    tight = replace(cfg, physics=replace(cfg.physics, max_element_stretch=1.000001))
    with pytest.raises(RuntimeError, match=r"diverged at frame 1: an element of the rope is .*x its rest length"):
        generate_dataset(tight, "rope", "tiny", tmp_path / "out", episodes=1, frames=8, progress=False)
    assert not (tmp_path / "out" / "rope_000").exists()
    world = yaml.safe_load((ROOT / "config/world/default.yaml").read_text())
    world["physics"]["max_element_stretch"] = 1.0
    world["robot"] = str(ROOT / "config/world/robot_panda.yaml")
    world["effects_config"] = str(ROOT / "config/world/effects.yaml")
    (tmp_path / "w.yaml").write_text(yaml.safe_dump(world))
    with pytest.raises(ValueError, match="max_element_stretch must be > 1"):
        load_world_config(tmp_path / "w.yaml")


# ----------------------------------------------------------------------------- robot from config


def test_robot_and_wrist_mount_come_from_config(cfg, tmp_path):
    robot = yaml.safe_load((ROOT / "config/world/robot_panda.yaml").read_text())
    robot["urdf"] = str(ROOT / "soma_ros/resources/robots/franka_panda/panda.urdf")
    robot["wrist_camera"] = {"parent": "panda_link8", "xyz": [0.05, 0.02, 0.01], "rpy": [0.1, -0.2, 0.3]}
    (tmp_path / "robot_x.yaml").write_text(yaml.safe_dump(robot))
    world = yaml.safe_load((ROOT / "config/world/default.yaml").read_text())
    world["robot"] = str(tmp_path / "robot_x.yaml")
    world["effects_config"] = str(ROOT / "config/world/effects.yaml")
    (tmp_path / "world_x.yaml").write_text(yaml.safe_dump(world))
    cfg_x = load_world_config(tmp_path / "world_x.yaml")
    m = generate_dataset(cfg_x, "rope", "tiny", tmp_path / "out", episodes=1, frames=8, progress=False)
    bag = read_bag(tmp_path / "out" / m["episodes"][0]["bag"])
    mount = [t for t in bag["/tf_static"][0][1].transforms if t.child_frame_id == "cam_wrist_color_optical_frame"]
    assert len(mount) == 1 and mount[0].header.frame_id == "panda_link8"
    T = tf_matrix(mount[0].transform)
    from soma_ros.world.transforms import rpy_to_mat

    assert np.allclose(T[:3, 3], [0.05, 0.02, 0.01]) and np.allclose(T[:3, :3], rpy_to_mat([0.1, -0.2, 0.3]))


def test_config_errors_are_one_line(tmp_path):
    from soma_ros.world import load_robot_config

    bad = yaml.safe_load((ROOT / "config/world/robot_panda.yaml").read_text())
    bad["grippr"] = bad.pop("gripper")
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(bad))
    with pytest.raises(ValueError, match="unknown key.*grippr"):
        load_robot_config(tmp_path / "bad.yaml")
    bad2 = yaml.safe_load((ROOT / "config/world/robot_panda.yaml").read_text())
    bad2["gripper"]["actuated"] = "panda_joint3"
    (tmp_path / "bad2.yaml").write_text(yaml.safe_dump(bad2))
    with pytest.raises(ValueError, match="gripper.actuated"):
        load_robot_config(tmp_path / "bad2.yaml")


# ----------------------------------------------------------------------------- CLI


def _soma(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "soma_ros.cli", *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)


def test_cli_help_and_errors(tmp_path):
    r = _soma("world", "--help")
    assert r.returncode == 0
    for word in ("--object", "--preset", "--effects", "--storage", "EVALUATION-ONLY", "/world/object_points", "manifest.json"):
        assert word in r.stdout
    r = _soma("world", "--object", "rope", "--out", str(tmp_path / "x"), "--effects", "wnd")
    assert r.returncode == 2 and "unknown effect 'wnd'" in r.stderr and r.stderr.count("\n") == 1
    r = _soma("world", "--object", "rope", "--out", str(tmp_path / "y"), "--task", "fold")
    assert r.returncode == 2 and "fold" in r.stderr and r.stderr.count("\n") == 1


def test_cli_generates(tmp_path):
    r = _soma("world", "--object", "rope", "--preset", "tiny", "--episodes", "1", "--frames", "8", "--quiet",
              "--effects", "wind", "--out", str(tmp_path / "d"))
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["episodes"] == 1 and summary["effects"] == ["wind"]
    m = json.loads((tmp_path / "d" / "manifest.json").read_text())
    assert m["effects"] == ["wind"]
    r = _soma("world", "--object", "rope", "--episodes", "1", "--frames", "8", "--quiet", "--out", str(tmp_path / "d"))
    assert r.returncode == 2 and "--overwrite" in r.stderr


def test_drop_lifts_the_rope_then_lets_it_fall_back_onto_the_table(cfg, tmp_path):
    """The ``drop`` task lifts as ``lift`` does, then opens the fingers (pick and let go): the rope's
    ground-truth points rise well off the table while held and lie on it at the end; the plan's
    release time is in the sidecar."""
    import copy

    c = copy.deepcopy(cfg)
    c.tasks["rope"] = ["drop"]
    m = generate_dataset(c, "rope", "tiny", tmp_path, episodes=1, seed=0, task="drop", frames=60, progress=False)
    ep = m["episodes"][0]
    assert ep["task"] == "drop"
    meta = json.loads((tmp_path / f"{ep['name']}.meta.json").read_text())
    release = meta["plan"]["release_time"]
    bag = read_bag(tmp_path / ep["bag"])
    top = np.array([np.frombuffer(msg.data, np.float32).reshape(-1, 3)[:, 2].max() for _, msg in bag[OBJECT_POINTS_TOPIC]])
    table = cfg.table.height
    assert top.max() > table + 0.08, top.max() - table  # carried up
    assert int(top.argmax()) < 0.8 * len(top)  # ... before the end
    assert top[-1] < table + 0.03, top[-1] - table  # let go: back on the table (radius 6.5 mm + resting)
    assert 0.0 < release < 59 / 30.0 and int(top.argmax()) >= int(release * 30.0) - 2  # highest about when it opens
    with pytest.raises(ValueError, match="unknown task"):
        bad = copy.deepcopy(cfg)
        bad.tasks["rope"] = ["throw"]
        bad.validate()
