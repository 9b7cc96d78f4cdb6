"""`soma resim` end to end on a tiny reference-world episode and a barely trained run:

* the output bag (read back with rosbags) holds every recorded topic unchanged and the
  simulated topics, one message per recorded frame, stamped like the recorded frames,
  with the right encodings, sizes, camera poses and splat layout;
* metrics.json equals what :mod:`soma_ros.evaluation.evaluate` computes for the same episode (also for
  a copy of the bag outside the dataset, whose initial state is aligned afresh);
* it runs without rclpy ever being imported (a subprocess);
* bad inputs give one-line errors and exit code 1.

Budget on 2 cores: about 15 s for the fixture (3 episodes of 10 frames, a 2-iteration
training run), a few seconds per resim.
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

ROOT = Path(__file__).resolve().parents[2]
TEST_EPISODE = "rope_000"  # the dataset's one test episode (seed 3)
SIM_TOPIC_KINDS = ("image_raw", "depth", "camera_info")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """(dataset, run): 3 tiny rope episodes of 10 frames and a `soma train --config tiny` run of 2 iterations."""
    from conftest import train_tiny_run

    root = tmp_path_factory.mktemp("resim")
    data = root / "data"
    train_tiny_run(data, root / "run", episodes=3, frames=10)
    man = json.loads((data / "manifest.json").read_text())
    assert {e["name"]: e["split"] for e in man["episodes"]}[TEST_EPISODE] == "test"
    return data, root / "run"


_CHILD = r"""
import json, sys
from soma_ros.cli import main
rc = main(sys.argv[1:])
print("RESULT " + json.dumps({"rc": rc, "rclpy": sorted(m for m in sys.modules if m == "rclpy" or m.startswith("rclpy."))}))
"""


@pytest.fixture(scope="module")
def resim_out(tiny_run, tmp_path_factory):
    """`soma resim` of the test episode (mcap), in a subprocess that reports the modules it imported."""
    data, run = tiny_run
    out = tmp_path_factory.mktemp("resim_out")
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MUJOCO_GL="egl")
    p = subprocess.run([sys.executable, "-c", _CHILD, "resim", "--checkpoint", str(run), "--bag",
                        str(data / TEST_EPISODE), "--out", str(out), "--quiet"],
                       env=env, capture_output=True, text=True, timeout=300)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    assert p.returncode == 0 and lines, p.stdout[-3000:] + p.stderr[-3000:]
    result = json.loads(lines[-1][len("RESULT "):])
    assert result["rc"] == 0, p.stderr[-3000:]
    return out, result, p.stdout


def _read(bag: Path) -> dict[str, list[tuple[int, bytes, str]]]:
    """{topic: [(bag time, raw CDR, msgtype)]} in bag order."""
    from rosbags.highlevel import AnyReader

    from soma_ros.bagtypes import typestore

    out: dict[str, list] = {}
    with AnyReader([bag], default_typestore=typestore()) as r:
        for conn, ts, raw in r.messages():
            out.setdefault(conn.topic, []).append((ts, bytes(raw), conn.msgtype))
    return out


def _msg(entry):
    from soma_ros.bagtypes import typestore

    _, raw, msgtype = entry
    return typestore().deserialize_cdr(raw, msgtype)


def _ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def test_rclpy_is_never_imported(resim_out):
    out, result, stdout = resim_out
    assert result["rclpy"] == [], f"resim imported {result['rclpy']}"
    assert "soma resim:" in stdout and "psnr=" in stdout


def test_output_bag_holds_recorded_and_simulated_topics(resim_out, tiny_run):
    from soma_ros.core.cloud_layout import POINT_STEP, SPLAT_FIELDS, cloud_to_splats
    from soma_ros.data.bags import decode_image
    from soma_ros.evaluation.evaluate import EvalContext

    data, run = tiny_run
    out, _, _ = resim_out
    bag_dir = out / "resim_bag"
    assert (bag_dir / "metadata.yaml").is_file() and list(bag_dir.glob("*.mcap")), list(bag_dir.iterdir())
    rec = _read(data / TEST_EPISODE)
    got = _read(bag_dir)

    # the recorded /tf (the robot's links) and the simulated one (world -> soma_sim -> cameras) share the topic
    sim_tf = [m for m in got["/tf"] if any(x.child_frame_id == "soma_sim" for x in _msg(m).transforms)]
    recorded = dict(got, **{"/tf": [m for m in got["/tf"] if m not in sim_tf]})
    # every recorded topic, message for message, byte for byte, same bag times
    for topic, msgs in rec.items():
        assert topic in got, topic
        assert [(ts, raw) for ts, raw, _ in recorded[topic]] == [(ts, raw) for ts, raw, _ in msgs], topic
    assert {"/joint_states", "/tf_static", "/world/object_points", "/cam_front/color/image_raw"} <= set(rec)

    ctx = EvalContext.from_run(run, data)
    ep = ctx.store.episode(TEST_EPISODE)
    init = ctx.store.initial_splats(TEST_EPISODE)
    T = ep.num_frames
    frame_stamps = [_ns(_msg(m).header) for m in rec["/cam_front/color/image_raw"]]
    assert T == 10 and frame_stamps == ep.stamps_ns.tolist()

    sim_topics = {t for t in got if t.startswith("/soma/")}
    expect = {f"/soma/{c}/{k}" for c in ep.camera_names for k in SIM_TOPIC_KINDS} | {"/soma/splats"}
    assert sim_topics == expect
    assert set(got) == set(rec) | expect | {"/tf"}
    assert len(got["/tf"]) == len(sim_tf) + len(rec.get("/tf", []))
    for topic in sorted(expect | {"/tf"}):
        msgs = sim_tf if topic == "/tf" else got[topic]
        assert len(msgs) == T, topic
        assert [ts for ts, _, _ in msgs] == frame_stamps, topic  # bag time = the recorded frame's stamp
        if topic != "/tf":
            assert [_ns(_msg(m).header) for m in msgs] == frame_stamps, topic

    for ci, cam in enumerate(ep.camera_names):
        info_rec = _msg(rec[f"/{cam}/color/camera_info"][0])
        frame = f"soma_sim/{cam}_optical"
        for t in range(T):
            img = _msg(got[f"/soma/{cam}/image_raw"][t])
            dep = _msg(got[f"/soma/{cam}/depth"][t])
            info = _msg(got[f"/soma/{cam}/camera_info"][t])
            assert (img.encoding, img.width, img.height, img.step) == ("rgb8", 160, 120, 480)
            assert (dep.encoding, dep.width, dep.height, dep.step) == ("32FC1", 160, 120, 640)
            assert img.header.frame_id == dep.header.frame_id == info.header.frame_id == frame
            assert (info.width, info.height) == (160, 120)
            np.testing.assert_allclose(np.asarray(info.k), np.asarray(info_rec.k))
        # frame 0 is the aligned initial state: the simulated object lies on the recorded object
        sim_rgb = decode_image(_msg(got[f"/soma/{cam}/image_raw"][0]), cam, ("rgb8",))
        sim_depth = decode_image(_msg(got[f"/soma/{cam}/depth"][0]), cam, ("32fc1",))
        drawn = sim_rgb.max(axis=-1) > 30
        obj = ep.object_mask[0, ci].numpy()
        assert drawn.sum() > 20 and obj.sum() > 20, cam
        assert (drawn & obj).sum() / drawn.sum() > 0.3, cam  # the camera pose and intrinsics are the recorded ones
        assert np.all(sim_depth[drawn] > 0.05)
        assert not (sim_depth == 0).any() and np.isnan(sim_depth[~drawn]).any()  # REP 118: NaN = nothing drawn
        rec_depth = ep.depth[0, ci].numpy()
        both = drawn & obj & (rec_depth > 0) & np.isfinite(sim_depth)
        assert np.median(np.abs(sim_depth[both] - rec_depth[both])) < 0.03, cam  # metres, like the recording

    # TF: world -> soma_sim (identity), soma_sim -> each camera at its recorded pose (the wrist camera moves)
    from soma_ros.data.bags import tf_to_matrix

    for t in (0, T - 1):
        tf = {(x.header.frame_id, x.child_frame_id): x for x in _msg(sim_tf[t]).transforms}
        np.testing.assert_allclose(tf_to_matrix(tf[("world", "soma_sim")].transform), np.eye(4), atol=1e-12)
        for ci, cam in enumerate(ep.camera_names):
            x = tf[("soma_sim", f"soma_sim/{cam}_optical")]
            assert _ns(x.header) == frame_stamps[t]
            np.testing.assert_allclose(tf_to_matrix(x.transform), ep.cam_to_world[t, ci].numpy(), atol=1e-6)

    # splats: the soma_msgs layout, every splat, frame 0 = the initial splats
    clouds = [_msg(m) for m in got["/soma/splats"]]
    assert [f.name for f in clouds[0].fields] == list(SPLAT_FIELDS)
    assert clouds[0].point_step == POINT_STEP and clouds[0].width == len(init) and clouds[0].header.frame_id == "soma_sim"
    s0 = cloud_to_splats(clouds[0])
    torch.testing.assert_close(s0.means, init.means.float(), atol=1e-6, rtol=0)
    torch.testing.assert_close(s0.colors(), init.colors().float(), atol=1e-5, rtol=0)
    assert all(c.width == len(init) for c in clouds)
    last = cloud_to_splats(clouds[-1])
    assert torch.isfinite(last.means).all()


def test_mcap_with_mcap_ros2_support_decodes_every_message_of_the_resim_bag(resim_out):
    """An independent reader (``mcap`` + ``mcap-ros2-support``'s CDR decoder, as Foxglove reads
    the file) decodes every message, recorded and simulated, with its schema."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out, _, _ = resim_out
    files = sorted((out / "resim_bag").glob("*.mcap"))
    assert files
    topics: dict[str, int] = {}
    total = 0
    for f in files:
        with open(f, "rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            total += reader.get_summary().statistics.message_count
            for _, ch, _, msg in reader.iter_decoded_messages():
                topics[ch.topic] = topics.get(ch.topic, 0) + 1
                if ch.topic.endswith("/depth"):
                    assert msg.encoding == "32FC1" and len(msg.data) == 4 * msg.width * msg.height
    assert total > 0 and sum(topics.values()) == total
    assert {"/soma/splats", "/tf", "/joint_states", "/soma/cam_front/depth"} <= set(topics)


def test_view_plays_the_resim_output_back(resim_out, tiny_run):
    """`soma view --resim`'s source: one frame per simulated cloud, each with the splats (coloured by
    their distance to the ground-truth points), the robot from the bag's /robot_description, and the
    recorded image beside the simulated one for every camera."""
    from soma_ros.viewer.resim import ResimSource
    from soma_ros.viewer.scene import TwinView

    data, run = tiny_run
    out, _, _ = resim_out
    view = TwinView(port=0)
    cams: dict = {}
    real_set_camera = view.set_camera
    view.set_camera = lambda name, *a, **k: (cams.__setitem__(name, k), real_set_camera(name, *a, **k))
    try:
        src = ResimSource(view, str(out), scene=str(run / "scene"))
        got = _read(out / "resim_bag")
        assert len(src.frames) == len(got["/soma/splats"]) == 10
        assert view._robot is not None
        src.show(len(src.frames) - 1)
        last = cloud_to_splats_raw(got["/soma/splats"][-1])
        np.testing.assert_allclose(view._splat_data[0], last.means.numpy(), atol=1e-5)
        err = view._error
        assert err is not None and err.shape == (len(last),) and np.all(err >= 0) and 0 < np.median(err) < 0.2
        assert set(cams) == {"cam_wrist", "cam_front", "cam_side"}
        for k in cams.values():
            assert k["sim_image"] is not None and k["real_image"] is not None
            assert k["sim_image"].shape == k["real_image"].shape == (120, 160, 3)
        assert "error to ground truth" in view._status.content
        src.stop()
    finally:
        view.close()


def cloud_to_splats_raw(entry):
    from soma_ros.core.cloud_layout import cloud_to_splats

    return cloud_to_splats(_msg(entry))


def test_metrics_equal_the_evaluation_harness(resim_out, tiny_run, tmp_path):
    from soma_ros.cli import main
    from soma_ros.evaluation.baselines import load_model
    from soma_ros.evaluation.evaluate import EvalConfig, EvalContext, evaluate_models
    from soma_ros.core.scoring import METRICS

    data, run = tiny_run
    out, _, _ = resim_out
    got = json.loads((out / "metrics.json").read_text())
    assert (out / "table.md").is_file() and (out / "sheets" / f"{TEST_EPISODE}.png").is_file()
    ref = evaluate_models({"run": load_model(run)}, EvalContext.from_run(run, data), "test", {"run": tmp_path / "ev"},
                          EvalConfig(contact_sheets=False, progress=False), log=lambda s: None)["run"]
    a, b = got["episodes"][TEST_EPISODE], ref["episodes"][TEST_EPISODE]
    assert a["frames"] == b["frames"] == 9
    for m in METRICS:
        assert a[m] == pytest.approx(b[m], rel=1e-9, abs=1e-12), m
        assert got["mean"][m] == pytest.approx(ref["mean"][m], rel=1e-9, abs=1e-12), m
        assert a["per_frame"][m] == pytest.approx(b["per_frame"][m], rel=1e-9, abs=1e-12), m
    assert all(np.isfinite(a[m]) for m in METRICS)  # Chamfer too: the bag has the ground truth
    r = got["resim"]
    assert r["episode"] == TEST_EPISODE and r["split"] == "test" and r["frames"] == 10 and r["storage"] == "mcap"
    assert r["simulated_topics"]["/soma/splats"] == 10

    # a copy of the bag outside the dataset: the initial state is aligned afresh, the scores are the same
    copy = tmp_path / "recorded_elsewhere"
    shutil.copytree(data / TEST_EPISODE, copy)
    dst = tmp_path / "copy_out"
    assert main(["resim", "--checkpoint", str(run / "checkpoint.pt"), "--bag", str(copy), "--out", str(dst),
                 "--storage", "sqlite3", "--cameras", "cam_front", "--no-sheets", "--quiet"]) == 0
    c = json.loads((dst / "metrics.json").read_text())
    assert c["resim"]["split"] == "resim" and c["resim"]["cameras"] == ["cam_front"]
    for m in METRICS:
        assert c["episodes"]["recorded_elsewhere"][m] == pytest.approx(b[m], rel=1e-6, abs=1e-9), m
    topics = _read(dst / "resim_bag")
    assert list((dst / "resim_bag").glob("*.db3"))
    expect = {f"/soma/cam_front/{k}" for k in SIM_TOPIC_KINDS} | {"/soma/splats"}
    assert {t for t in topics if t.startswith("/soma/")} == expect


def _copy_bag(src: Path, dst: Path, drop=(), rewrite=None) -> Path:
    """A copy of a bag without the ``drop`` topics and with ``rewrite[topic](msg)`` applied."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Writer

    from soma_ros.bagtypes import typestore

    store = typestore()
    rewrite = rewrite or {}
    with AnyReader([src], default_typestore=store) as r, Writer(dst, version=9) as w:
        conns = {c.id: w.add_connection(c.topic, c.msgtype, typestore=store) for c in r.connections if c.topic not in drop}
        for conn, ts, raw in r.messages():
            if conn.id not in conns:
                continue
            if conn.topic in rewrite:
                raw = store.serialize_cdr(rewrite[conn.topic](store.deserialize_cdr(raw, conn.msgtype)), conn.msgtype)
            w.write(conns[conn.id], ts, raw)
    return dst


def test_bad_inputs_are_one_line_errors(tiny_run, tmp_path, capsys):
    from soma_ros.cli import main

    data, run = tiny_run
    bag = data / TEST_EPISODE

    def fails(args: list[str], *needles: str) -> None:
        capsys.readouterr()
        rc = main(["resim", "--checkpoint", str(run), "--out", str(tmp_path / "out"), "--quiet", *args])
        err = capsys.readouterr().err.strip()
        assert rc == 2, (args, err)
        assert err.startswith("soma resim: error: ") and "\n" not in err and "Traceback" not in err, err
        for n in needles:
            assert n in err, (n, err)

    fails(["--bag", str(tmp_path / "no_such_bag")], "bag not found")
    fails(["--bag", str(data)], "not a rosbag2 folder")
    fails(["--bag", str(_copy_bag(bag, tmp_path / "no_js", drop={"/joint_states"}))], "no /joint_states topic")

    def rename(msg):
        msg.name = [f"arm_{n}" for n in msg.name]
        return msg

    fails(["--bag", str(_copy_bag(bag, tmp_path / "renamed", rewrite={"/joint_states": rename}))],
          "/joint_states does not fit the robot", "panda_joint1")
    fails(["--bag", str(bag), "--cameras", "cam_front,cam_top"], "unknown camera(s) cam_top", "cam_wrist")
    other = tmp_path / "arx_scene"
    shutil.copytree(run / "scene", other)
    meta = json.loads((other / "scene.json").read_text())
    meta["robot"]["config"] = "arx5"
    (other / "scene.json").write_text(json.dumps(meta))
    fails(["--bag", str(bag), "--scene", str(other)], "trained for robot 'panda'", "'arx5'")
    (tmp_path / "out" / "resim_bag").mkdir(parents=True)
    fails(["--bag", str(bag)], "already exists", "--force")
    assert not (tmp_path / "out" / "metrics.json").exists()
