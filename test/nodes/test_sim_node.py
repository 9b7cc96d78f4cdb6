"""soma_sim_node as its own OS process, driven by this test over real ROS 2 topics.

The test plays the robot: it publishes /joint_states from its own rclpy context
(LiveProbe, benchmarks/bench_live.py) and checks what the node publishes. Each
test gets its own ROS_DOMAIN_ID with LOCALHOST discovery (conftest fixtures).

Scene: the test run's untrained run (random-weight `cpu` model, 2,000-splat
synthetic rope, 160x120, cam_front fixed + cam_wrist on panda_hand). Its initial
state is an exact fixed point, so while the gripper stays out of the robot
effect's reach (5 cm) the published splats are bit-exactly the initial ones --
a sharp probe for "bad input was not used". The trained-model lift test trains
a tiny model with the trainer (``config/train/tiny.yaml``) on a tiny reference-
world rope dataset once per test run.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import ROOT, recorded_grasp, sim_node_args
from soma_ros.nodes.testing import RosProcess

SIM = "soma_ros.nodes.sim_node"
TABLE_Z = 0.75
W, H = 160, 120
START_TIMEOUT = 90.0  # a cold node start imports torch and rclpy and builds the model: seconds on a busy CI box


# --------------------------------------------------------------------------- fixtures and helpers
@pytest.fixture(scope="module")
def kin(untrained_run):
    """The engine in this process (for FK/IK, reference renders), and joint vectors."""
    from benchmarks.bench_live import Poser
    from soma_ros.live import load_live

    live = load_live(str(untrained_run[0]), str(untrained_run[1]))
    poser = Poser(live.robot, live.base_to_sim.matrix(), live.required_joints, live.bundle.gravity)
    m = live.bundle.splats.means.double().numpy()
    x_lo, x_hi = float(m[:, 0].min()), float(m[:, 0].max())
    grasp = (x_lo + 0.25 * (x_hi - x_lo), float(np.median(m[:, 1])), float(np.median(m[:, 2])))
    hover = poser.solve((0.5, 0.02, TABLE_Z + 0.25))  # 25 cm above the rope: out of reach, wrist camera sees it
    descent = poser.line((grasp[0], grasp[1], grasp[2] + 0.12), grasp, 30, q0=hover)
    return {"live": live, "poser": poser, "hover": hover, "descent": descent, "in_rope": descent[-1],
            "x0": live.snapshot()[0].means.double().numpy()}


@contextmanager
def sim_node(ros_env, run, *params: str):
    args = sim_node_args(run[0], run[1], *[a for p in params for a in ("-p", p)])
    node = RosProcess(SIM, args, ros_env, name="sim_node")
    try:
        yield node
    finally:
        rc = node.stop()  # always; on a failure in the body that failure is what is reported
    assert rc in (0, -2), f"soma_sim_node exited with {rc} (0 or -2 on SIGINT expected)\n{node.output()[-4000:]}"


@pytest.fixture
def probe(ros_context, kin):
    from benchmarks.bench_live import LiveProbe

    p = LiveProbe(ros_context, kin["live"].required_joints, cameras=("cam_front", "cam_wrist"), depth=True,
                  info=True, tf_static=True)
    try:
        yield p
    finally:
        p.close()


def _started(probe, node, vec, key=("status",), timeout=START_TIMEOUT):
    """Feed `vec` until the node publishes on `key`; fail with the node's output otherwise."""
    ok = probe.hold(vec, lambda: (probe.count.get(key, 0) > 0 and probe.count.get(("status",), 0) > 0)
                    or not node.alive(), timeout)
    assert ok and node.alive(), f"no {key} from soma_sim_node\n{node.output()[-4000:]}"


def _means(cloud) -> np.ndarray:
    from benchmarks.bench_live import cloud_means

    return cloud_means(cloud)


def _accepted(st) -> int:
    return int(st.joint_states_received) - int(st.joint_states_rejected)


def _rejected_log_lines(node) -> list[str]:
    return [ln for ln in node.output().splitlines() if "rejected /joint_states" in ln]


# --------------------------------------------------------------------------- outputs
def test_images_splats_camera_info_status_and_tf(ros_env, untrained_run, probe, kin):
    from soma_ros.core.cloud_layout import POINT_STEP, SPLAT_FIELDS, FLOAT32, cloud_to_splats, unpack_rgb, splats_to_records

    live = kin["live"]
    with sim_node(ros_env, untrained_run) as node:
        _started(probe, node, kin["hover"])
        keys = [("image", "cam_front"), ("image", "cam_wrist"), ("depth", "cam_front"), ("info", "cam_front"),
                ("splats",), ("tf_static",)]
        assert probe.hold(kin["hover"], lambda: all(probe.count.get(k, 0) for k in keys) and
                          probe.last_status().state == "running", 60), (probe.count, node.output()[-3000:])
        # fresh messages, all produced while the gripper hovers out of reach
        n_img = probe.count[("image", "cam_front")]
        assert probe.hold(kin["hover"], lambda: probe.count[("image", "cam_front")] > n_img + 1, 30)
        img, img_w = probe.last("image", "cam_front"), probe.last("image", "cam_wrist")
        depth, info, cloud, st = probe.last("depth", "cam_front"), probe.last("info", "cam_front"), probe.last("splats"), probe.last_status()

        # ---- image: size, encoding, frame, content
        assert (img.width, img.height, img.encoding, img.step) == (W, H, "rgb8", 3 * W)
        assert img.header.frame_id == "soma_sim/cam_front_optical"
        rgb = np.frombuffer(bytes(img.data), np.uint8).reshape(H, W, 3)
        obj = rgb.max(-1) > 12
        assert 0.01 < obj.mean() < 0.9, f"object pixels: {obj.mean():.3f}"
        # the content is the rope at rest: the same render made here, to one grey level
        state, template, _ = live.snapshot()
        ref, _ = live.render(state, template, kin["hover"])
        ref_rgb = (ref.rgb[0].clamp(0, 1) * 255).round().to(torch.uint8).numpy()
        assert np.abs(rgb.astype(int) - ref_rgb.astype(int)).max() <= 1
        # the object's colour is the rope's (mean splat colour), not a constant fill
        rope_rgb = template.colors().mean(0).numpy()
        assert np.abs(rgb[obj].mean(0) / 255.0 - rope_rgb).max() < 0.2
        wrist = np.frombuffer(bytes(img_w.data), np.uint8).reshape(H, W, 3)
        assert (wrist.max(-1) > 12).mean() > 0.01 and img_w.header.frame_id == "soma_sim/cam_wrist_optical"

        # ---- depth: 32FC1 metres, where the object is
        assert (depth.width, depth.height, depth.encoding, depth.step) == (W, H, "32FC1", 4 * W)
        d = np.frombuffer(bytes(depth.data), np.float32).reshape(H, W)
        hit = np.isfinite(d)  # REP 118: NaN where no splat was drawn, never 0
        assert not (d == 0).any() and (hit & obj).sum() > 0.8 * obj.sum()
        assert 0.4 < float(np.median(d[hit])) < 1.5  # cam_front is ~0.8 m from the rope
        assert np.allclose(np.nan_to_num(d), ref.depth[0].numpy(), atol=1e-4)

        # ---- camera_info: the bundle's intrinsics, pixel centres at integers (the bundle's
        # principal point W/2, H/2 from the image edge is (W-1)/2, (H-1)/2 in CameraInfo)
        K = np.array(info.k).reshape(3, 3)
        assert (info.width, info.height, info.distortion_model) == (W, H, "plumb_bob")
        assert np.allclose(K, [[0.9 * W, 0, (W - 1) / 2], [0, 0.9 * W, (H - 1) / 2], [0, 0, 1]])
        assert info.header.frame_id == "soma_sim/cam_front_optical"

        # ---- splats: count, layout, positions, packed rgb
        assert (cloud.width, cloud.height, cloud.point_step, cloud.row_step) == (2000, 1, POINT_STEP, POINT_STEP * 2000)
        assert [f.name for f in cloud.fields] == list(SPLAT_FIELDS)
        assert all(f.offset == 4 * i and f.datatype == FLOAT32 and f.count == 1 for i, f in enumerate(cloud.fields))
        assert cloud.header.frame_id == "soma_sim" and not cloud.is_bigendian
        sp = cloud_to_splats(cloud)
        assert np.array_equal(_means(cloud), state.means.float().double().numpy())  # at rest, bit-exact
        assert torch.allclose(sp.opacities, template.opacities.float()) and torch.allclose(sp.sh_dc, template.sh_dc.float())
        rec = np.frombuffer(bytes(cloud.data), np.uint8).view(np.dtype({"names": ["rgb"], "formats": ["<f4"],
                                                                       "offsets": [56], "itemsize": 64}))
        assert np.array_equal(unpack_rgb(rec["rgb"]), unpack_rgb(splats_to_records(template)["rgb"]))

        # ---- status
        assert st.state == "running" and st.num_splats == 2000 and st.header.frame_id == "soma_sim"
        assert st.step > 0 and st.step_time_ms > 0 and st.render_time_ms > 0
        # in-node CPU times and the engine's own times (measured alone at start-up)
        assert st.engine_step_ms > 0 and st.engine_render_ms > 0
        seen = [m for _, m in probe.status]
        assert max(m.step_cpu_ms for m in seen) > 0 and max(m.render_cpu_ms for m in seen) > 0
        assert st.step_rate_hz > 0 and st.image_rate_hz > 0
        assert st.joint_states_received > 0 and st.joint_states_rejected == 0
        s0 = st.step
        assert probe.hold(kin["hover"], lambda: probe.last_status().step > s0 + 3, 30)

        # ---- tf_static: world -> soma_sim (identity)
        tf = probe.last("tf_static").transforms[0]
        assert (tf.header.frame_id, tf.child_frame_id) == ("world", "soma_sim")
        assert tf.transform.rotation.w == pytest.approx(1.0) and tf.transform.translation.z == pytest.approx(0.0)
        assert node.alive()


# --------------------------------------------------------------------------- reset
def _rope_cloud(n, center, seed):
    from soma_ros.core.scenes import synthetic_rope
    from soma_ros.nodes.conversions import splats_to_cloud

    s = synthetic_rope(n, center=center, seed=seed)
    return s, splats_to_cloud(s, "soma_sim")


def _malformed_clouds():
    from sensor_msgs.msg import PointCloud2

    from soma_ros.core.scenes import synthetic_rope
    from soma_ros.nodes.conversions import splats_to_cloud

    base = splats_to_cloud(synthetic_rope(800, center=(0.4, 0.1, TABLE_Z), seed=4), "soma_sim")

    def variant(**kw):
        from soma_ros.nodes.testing import cloud_variant

        return cloud_variant(base, **kw)

    nan = np.frombuffer(bytes(base.data), np.float32).copy().reshape(800, 16)
    nan[5, 0] = np.nan
    neg = np.frombuffer(bytes(base.data), np.float32).copy().reshape(800, 16)
    neg[9, 3] = -0.01  # scale_0
    return [
        ("empty cloud", variant(width=0, data=b""), "neither splats (0 points) nor a ply_path"),
        ("missing opacity field", variant(fields=[f for f in base.fields if f.name != "opacity"]), "lacks required fields: opacity"),
        ("NaN means", variant(data=nan.tobytes()), "non-finite"),
        ("truncated data", variant(data=bytes(base.data)[:-100]), "expected"),
        ("negative scale", variant(data=neg.tobytes()), "scales must be > 0"),
        ("big-endian", variant(is_bigendian=True), "big-endian"),
    ]


def test_reset_with_a_new_scene_and_refused_resets(ros_env, untrained_run, probe, kin, tmp_path):
    with sim_node(ros_env, untrained_run, "render_rate_hz:=0.0", "splat_rate_hz:=10.0") as node:
        _started(probe, node, kin["hover"], key=("splats",))
        assert probe.last("splats").width == 2000

        new, msg = _rope_cloud(3000, center=(0.42, 0.08, TABLE_Z), seed=11)
        resp = probe.reset(splats_msg=msg)
        assert resp.success and resp.num_splats == 3000, resp.message
        assert resp.message == "scene reset: 3000 splats"
        assert probe.hold(kin["hover"], lambda: probe.last("splats").width == 3000, 30), node.output()[-3000:]
        assert np.allclose(_means(probe.last("splats")), new.means.double().numpy(), atol=1e-6)
        assert probe.hold(kin["hover"], lambda: probe.last_status().num_splats == 3000, 10)
        step_after_reset = probe.last_status().step

        for name, bad, reason in _malformed_clouds():
            resp = probe.reset(splats_msg=bad)
            assert not resp.success, name
            assert resp.num_splats == 3000, name
            assert resp.message.startswith("reset refused:") and reason in resp.message, (name, resp.message)
        resp = probe.reset(ply_path=str(tmp_path / "nope.ply"))
        assert not resp.success and "no scene this node may read" in resp.message and resp.num_splats == 3000

        # the old scene keeps running: same splats, steps go on
        n0 = probe.count[("splats",)]
        assert probe.hold(kin["hover"], lambda: probe.count[("splats",)] > n0 + 1, 30)
        assert probe.last("splats").width == 3000
        assert np.allclose(_means(probe.last("splats")), new.means.double().numpy(), atol=1e-6)
        assert probe.last_status().step > step_after_reset and probe.last_status().num_splats == 3000
        assert node.alive()
        assert len(re.findall(r"reset refused", node.output())) >= 7

        # back to the original scene from its file (the ply_path route)
        resp = probe.reset(ply_path=str(untrained_run[1]))
        assert resp.success and resp.num_splats == 2000, resp.message
        assert probe.hold(kin["hover"], lambda: probe.last("splats").width == 2000, 30)
        assert np.allclose(_means(probe.last("splats")), kin["x0"], atol=1e-6)


def test_reset_with_an_initial_joint_state_restarts_at_rest(ros_env, untrained_run, probe, kin):
    """After the gripper has pushed the rope, a reset carrying the hover pose as its initial
    joint state restarts the scene at exact rest: no step that sampled the old pose before
    the reset is applied after it (the node steps as fast as it can here, so a step is
    nearly always in flight when the reset arrives). A reset with a bad initial joint state
    is refused and keeps the joint states the node had."""
    with sim_node(ros_env, untrained_run, "rate_hz:=200.0", "render_rate_hz:=0.0", "splat_rate_hz:=10.0") as node:
        _started(probe, node, kin["hover"], key=("splats",))
        x_rest = _means(probe.last("splats"))
        for trial in range(3):
            probe.play(kin["descent"], hz=30)
            n0 = probe.count[("splats",)]
            assert probe.spin_until(lambda: probe.count[("splats",)] > n0, 30)
            assert not np.array_equal(_means(probe.last("splats")), x_rest), "the descent did not move the rope"
            resp = probe.reset(ply_path=str(untrained_run[1]), initial_joint_state=probe.joint_msg(kin["hover"]))
            assert resp.success, resp.message
            n0 = probe.count[("splats",)]
            assert probe.spin_until(lambda: probe.count[("splats",)] > n0 + 2, 30)  # nothing published meanwhile
            assert np.array_equal(_means(probe.last("splats")), x_rest), f"trial {trial}: not at rest after the reset"

        bad = probe.joint_msg(kin["hover"])
        bad.position[2] = math.nan
        resp = probe.reset(ply_path=str(untrained_run[1]), initial_joint_state=bad)
        assert not resp.success and "non-finite values for: panda_joint3" in resp.message, resp.message
        k0 = len(probe.status)
        assert probe.spin_until(lambda: len(probe.status) > k0 + 20, 30)
        assert all(m.state == "running" for _, m in list(probe.status)[k0:])  # the joint states were kept
        assert node.alive()


# --------------------------------------------------------------------------- bad input
def _bad_joint_states(probe, kin):
    """(kind, kwargs for probe.publish) -- each would put the gripper into the rope if it were used."""
    names = list(kin["live"].required_joints) + ["panda_finger_joint2"]
    v = list(kin["in_rope"]) + [kin["in_rope"][-1]]

    def with_value(i, x):
        p = list(v)
        p[i] = x
        return p

    now = probe.now_ns()
    return [
        ("nan", dict(names=names, positions=with_value(2, math.nan))),
        ("+inf", dict(names=names, positions=with_value(0, math.inf))),
        ("-inf", dict(names=names, positions=with_value(7, -math.inf))),
        ("beyond float32", dict(names=names, positions=with_value(1, 1e300))),
        ("fewer positions", dict(names=names, positions=v[:-2])),
        ("more positions", dict(names=names, positions=v + [0.0, 0.0])),
        ("unknown names", dict(names=[f"joint_{i}" for i in range(len(v))], positions=v)),
        ("missing joint", dict(names=names[1:], positions=v[1:])),
        ("duplicate name", dict(names=names[:3] + [names[2]] + names[4:], positions=v)),
        ("stamp backwards", dict(names=names, positions=v, stamp_ns=now - 5 * 10**9)),
        ("stamp an hour ahead", dict(names=names, positions=v, stamp_ns=now + 3600 * 10**9)),
    ]


def test_bad_joint_states_are_rejected_logged_and_survived(ros_env, untrained_run, probe, kin):
    """NaN/inf values, wrong lengths, unknown names, duplicates, stamps going backwards and
    stamps far ahead: each rejected and counted, logged (throttled), never used (the rope,
    which moves as soon as the gripper reaches it, stays bit-exactly still), and the
    correctly stamped stream that follows is taken again (input_rate_hz above the burst's rate:
    every message is taken, none dropped for a newer one)."""
    with sim_node(ros_env, untrained_run, "render_rate_hz:=0.0", "splat_rate_hz:=10.0", "input_rate_hz:=2000.0") as node:
        _started(probe, node, kin["hover"], key=("splats",))
        assert probe.hold(kin["hover"], lambda: _accepted(probe.last_status()) >= 5, 30)
        st0 = probe.last_status()
        x_rest = _means(probe.last("splats"))

        rounds, n_bad, n_good = 20, 0, 0
        t_start = time.monotonic()
        for r in range(rounds):  # ~200 Hz: the node's sensor-data subscription keeps 5, bursts would drop
            probe.publish(kin["hover"])
            n_good += 1
            probe.spin_for(0.005)
            for kind, kw in _bad_joint_states(probe, kin):
                probe.publish(**kw)
                n_bad += 1
                probe.spin_for(0.005)

        def counts():
            st = probe.last_status()
            return f"sent {n_bad} bad + {n_good} good; node: received {st.joint_states_received - st0.joint_states_received}, " \
                   f"rejected {st.joint_states_rejected - st0.joint_states_rejected}\n{node.output()[-3000:]}"

        assert probe.hold(kin["hover"], lambda: int(probe.last_status().joint_states_rejected) - int(st0.joint_states_rejected)
                          >= 0.9 * n_bad, 30), counts()
        # after the burst (which ended with a stamp an hour ahead), correct messages are taken again
        st1 = probe.last_status()
        assert probe.hold(kin["hover"], lambda: _accepted(probe.last_status()) >= _accepted(st1) + 10, 30), counts()
        st2 = probe.last_status()
        rejected = int(st2.joint_states_rejected) - int(st0.joint_states_rejected)
        assert rejected <= n_bad  # only the bad ones
        assert st2.state == "running" and st2.step > st0.step

        # nothing bad was used: the rope has not moved at all
        n0 = probe.count[("splats",)]
        assert probe.hold(kin["hover"], lambda: probe.count[("splats",)] > n0, 30)
        assert np.array_equal(_means(probe.last("splats")), x_rest)

        # logged, throttled (2 s per call site), with the reason
        elapsed = time.monotonic() - t_start
        lines = _rejected_log_lines(node)
        assert 1 <= len(lines) <= elapsed / 2.0 + 2, lines
        assert any(re.search(r"non-finite|names but|missing joints|duplicate|backwards|ahead of the clock", ln) for ln in lines)
        assert node.alive()


def test_a_1khz_joint_state_flood_is_survived_with_bounded_memory(ros_env, untrained_run, probe, kin):
    """5 s of /joint_states at 1 kHz (one in ten with a NaN) into a node that renders both
    cameras at 10 Hz: it keeps stepping, counts, logs throttled, and its RSS stays bounded.
    (The 30 s flood with figures is in benchmarks/bench_live.py.)"""
    from benchmarks.bench_live import rss_mb

    flood_s, hz = 5.0, 1000.0
    with sim_node(ros_env, untrained_run) as node:
        _started(probe, node, kin["hover"], key=("image", "cam_front"))
        # warm up: every code path (render, splats, status, rejects) has run once
        probe.publish(names=["x"], positions=[1.0, 2.0])
        assert probe.hold(kin["hover"], lambda: probe.last_status().joint_states_rejected >= 1, 30)
        probe.hold(kin["hover"], lambda: False, 1.0)
        st0 = probe.last_status()
        published0 = probe.published
        rss0 = rss_mb(node.proc.pid)
        names = list(kin["live"].required_joints) + ["panda_finger_joint2"]
        good = list(kin["hover"]) + [kin["hover"][-1]]
        bad = list(good)
        bad[3] = math.nan
        t0 = time.monotonic()
        sent = 0
        rss_peak = rss0
        next_rss = t0 + 0.5
        while (now := time.monotonic()) < t0 + flood_s:
            due = int((now - t0) * hz) + 1
            while sent < due:
                probe.publish(names=names, positions=bad if sent % 10 == 9 else good)
                sent += 1
            probe.executor.spin_once(timeout_sec=0)
            if now >= next_rss:
                rss_peak = max(rss_peak, rss_mb(node.proc.pid))
                next_rss += 0.5
        elapsed = time.monotonic() - t0
        assert node.alive(), node.output()[-3000:]
        # the node drains what it got; then the counters are final
        assert probe.hold(kin["hover"], lambda: probe.last_status().joint_states_received > st0.joint_states_received + 0.05 * sent, 30)
        probe.hold(kin["hover"], lambda: False, 1.0)
        st1 = probe.last_status()
        rss1 = rss_mb(node.proc.pid)
        received = int(st1.joint_states_received) - int(st0.joint_states_received)
        rejected = int(st1.joint_states_rejected) - int(st0.joint_states_rejected)
        print(f"\nflood: sent {sent} in {elapsed:.1f} s ({sent / elapsed:.0f} Hz), node received {received}, "
              f"rejected {rejected}; steps {st1.step - st0.step}; RSS {rss0:.0f} -> peak {rss_peak:.0f} -> {rss1:.0f} MB")
        assert sent >= 0.5 * flood_s * hz  # this process keeps ~1 kHz; on a starved CPU at least 500 Hz
        # A best-effort subscription (depth 5) drops what the executor cannot take in time: on 2
        # shared cores the node takes ~30% of a 1 kHz stream (figures: benchmarks/bench_live.py).
        assert 0.05 * sent <= received <= sent + 200  # + the hover messages of the waits
        # the node takes at most input_rate_hz (200) a second: every other message is counted as
        # dropped (from the publisher's sequence numbers), so received + dropped is what was published
        dropped = int(st1.joint_states_dropped) - int(st0.joint_states_dropped)
        published = probe.published - published0
        assert abs(received + dropped - published) <= 20, (received, dropped, published)
        assert 1 <= rejected <= 0.25 * received + 5  # the NaN ones (1 in 10 of the flood, none of the waits)
        assert st1.step - st0.step >= flood_s  # kept stepping (liveness, not a speed check)
        assert st1.state == "running"
        lines = _rejected_log_lines(node)
        assert 1 <= len(lines) <= (time.monotonic() - t0) / 2.0 + 3, len(lines)
        assert max(rss_peak, rss1) - rss0 < 64.0, (rss0, rss_peak, rss1)
        assert node.alive()


# --------------------------------------------------------------------------- the robot moves the object
def test_gripper_out_of_reach_keeps_the_rope_still_and_through_it_moves_it(ros_env, untrained_run, probe, kin):
    """What an untrained model can show over the node: while the gripper moves above the rope
    out of reach, /soma/splats stays bit-exactly the initial scene; moving it down into the
    rope changes /soma/splats (finite)."""
    with sim_node(ros_env, untrained_run, "render_rate_hz:=0.0", "splat_rate_hz:=10.0") as node:
        _started(probe, node, kin["hover"], key=("splats",))
        x_rest = _means(probe.last("splats"))
        assert np.allclose(x_rest, kin["x0"], atol=1e-6)
        above = kin["poser"].line((0.35, 0.02, TABLE_Z + 0.08), (0.62, 0.02, TABLE_Z + 0.08), 20, q0=kin["hover"])
        probe.play(above + above[::-1], hz=30)
        n0 = probe.count[("splats",)]
        assert probe.hold(above[0], lambda: probe.count[("splats",)] > n0, 30)
        assert np.array_equal(_means(probe.last("splats")), x_rest)

        probe.play(kin["descent"], hz=30)
        n0 = probe.count[("splats",)]
        assert probe.hold(kin["in_rope"], lambda: probe.count[("splats",)] > n0 + 1, 30)
        x = _means(probe.last("splats"))
        assert np.isfinite(x).all()
        assert float(np.linalg.norm(x - x_rest, axis=1).max()) > 1e-3, "the gripper went into the rope and nothing moved"
        st = probe.last_status()
        assert st.state == "running" and st.joint_states_rejected == 0
        assert node.alive()


def test_a_step_that_leaves_the_workspace_restarts_the_scene_and_is_counted(ros_env, untrained_run, probe, kin):
    """Divergence guard: with max_object_travel_m at 5 mm, pushing the rope further than that
    makes the step fail as diverged; the node logs it, restarts the scene from its initial
    state (counted in /soma/status), never publishes the runaway state, and keeps going."""
    travel = 0.005
    with sim_node(ros_env, untrained_run, "render_rate_hz:=0.0", "splat_rate_hz:=20.0",
                  f"max_object_travel_m:={travel}") as node:
        _started(probe, node, kin["hover"], key=("splats",))
        assert probe.hold(kin["hover"], lambda: probe.last_status().step > 10, 30)
        assert probe.last_status().failure_restarts == 0  # at rest: nothing to catch
        x0 = kin["x0"]
        center = x0.mean(0)
        limit = float(np.linalg.norm(x0 - center, axis=1).max()) + travel
        states = set()
        worst = {"d": 0.0}

        def watch() -> bool:
            st = probe.last_status()
            states.add(st.state)
            worst["d"] = max(worst["d"], float(np.linalg.norm(_means(probe.last("splats")) - center, axis=1).max()))
            return st.failure_restarts >= 3

        probe.play(kin["descent"], hz=30)
        assert probe.hold(kin["in_rope"], watch, 60), node.output()[-3000:]
        assert "restarted_after_failure" in states and probe.last_status().state in ("running", "restarted_after_failure")
        assert worst["d"] <= limit + 1e-6, (worst["d"], limit)  # no published cloud left the bound
        assert re.search(r"step failed \(a splat is .* outside the initial scene's bounding sphere", node.output())
        assert node.alive()


def test_parameters_file_in_config_matches_the_node_and_starts_it(ros_env, untrained_run, probe, kin, ros_context):
    """config/nodes/sim_node.yaml lists every parameter the node declares with the node's own
    default, and `--params-file` plus the two required -p start a node that uses the file."""
    import yaml
    from rclpy.parameter import Parameter
    from soma_ros.nodes.sim_node import SomaSimNode

    path = ROOT / "config" / "nodes" / "sim_node.yaml"
    params = yaml.safe_load(path.read_text())["/**"]["ros__parameters"]  # any node name
    node = SomaSimNode(context=ros_context, parameter_overrides=[
        Parameter("checkpoint", value=str(untrained_run[0])), Parameter("scene", value=str(untrained_run[1]))])
    try:
        declared = {n: p.value for n, p in node._parameters.items()
                    if n not in ("use_sim_time", "start_type_description_service")}  # rclpy's own
    finally:
        node.destroy_node()
    assert set(declared) == set(params), set(declared) ^ set(params)
    for name, value in params.items():
        if name in ("checkpoint", "scene"):
            continue
        got = declared[name]
        assert (list(got) if isinstance(value, list) else got) == value, (name, got, value)

    # a file keyed like the shipped one that changes the prefix and switches images off, used by
    # a real node under a remapped name and namespace
    custom = dict(params, topic_prefix="/twin", render_rate_hz=0.0)
    f = Path(ros_env.get("TMPDIR", "/tmp")) / f"sim_node_params_{os.getpid()}.yaml"
    f.write_text(yaml.safe_dump({"/**": {"ros__parameters": custom}}))
    args = ["--ros-args", "-r", "__node:=twin_of_cell_3", "-r", "__ns:=/cell3", "--params-file", str(f),
            "-p", f"checkpoint:={untrained_run[0]}", "-p", f"scene:={untrained_run[1]}"]
    proc = RosProcess(SIM, args, ros_env, name="sim_node_params")
    try:
        from soma_msgs.msg import SimStatus

        got = []
        sub = probe.node.create_subscription(SimStatus, "/twin/status", got.append, 10)
        assert probe.hold(kin["hover"], lambda: len(got) > 3 or not proc.alive(), START_TIMEOUT), proc.output()[-3000:]
        assert got[-1].state == "running" and got[-1].image_rate_hz == 0.0
        assert ("twin_of_cell_3", "/cell3") in probe.node.get_node_names_and_namespaces()
        probe.node.destroy_subscription(sub)
    finally:
        proc.stop()
        f.unlink(missing_ok=True)


# --------------------------------------------------------------------------- trained model: lift
TRAIN_CONFIG = ROOT / "config" / "train" / "tiny.yaml"
TRAINER = ROOT / "soma_ros" / "training" / "train.py"


@pytest.fixture(scope="session")
def trained_run(tmp_path_factory):
    """(checkpoint, scene dir, dataset dir): a tiny model trained on a tiny rope lift dataset.

    ``soma world --object rope --preset tiny --task lift --episodes 4`` (~12 s), then
    ``soma train --config config/train/tiny.yaml`` (~2.5 min on 2 cores). Through the
    ``soma train`` command when it exists, else the trainer's Python entry point (the
    same function the command calls).
    """
    if not (TRAINER.is_file() and TRAIN_CONFIG.is_file()):
        pytest.skip("soma_ros/training/train.py or config/train/tiny.yaml missing")
    from soma_ros.nodes.testing import ros_env as make_env, unique_domain_id

    root = tmp_path_factory.mktemp("trained")
    data, run = root / "world", root / "run"
    env = make_env(unique_domain_id())
    r = subprocess.run([sys.executable, "-m", "soma_ros.cli", "world", "--object", "rope", "--preset", "tiny",
                        "--task", "lift", "--episodes", "4", "--seed", "0", "--out", str(data), "--quiet"],
                       env=env, capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    if (ROOT / "soma_ros" / "commands" / "train.py").is_file():
        cmd = [sys.executable, "-m", "soma_ros.cli", "train", "--data", str(data), "--config", str(TRAIN_CONFIG),
               "--out", str(run), "--quiet"]
    else:
        cmd = [sys.executable, "-c", "import sys; from pathlib import Path; "
               "from soma_ros.training.config import load_train_config; from soma_ros.training.train import train; "
               "train(load_train_config(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), log=lambda *a, **k: None)",
               str(TRAIN_CONFIG), str(data), str(run)]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1200, cwd=ROOT)
    assert r.returncode == 0 and (run / "checkpoint.pt").is_file(), r.stdout[-3000:] + r.stderr[-3000:]
    return run / "checkpoint.pt", run / "scene", data


def test_trained_model_a_lift_of_the_gripper_lifts_the_grasped_part(ros_env, ros_context, trained_run):
    """The node runs the tiny trained model on its scene (the first frame of the first
    training episode); the test replays that episode's recorded /joint_states (descend,
    close on the rope, lift ~12 cm, hold), one physics step per recorded pose (as the
    recording's 30 FPS, whatever the node's step rate). In /soma/splats the grasped part --
    the splats within 3 cm of the gripper when it closes -- rises, and more than the far
    part (splats over 15 cm away; in the reference world's ground truth of this episode
    the grasped part rises 12.0 cm and that far part 5.0 cm: the rope hangs from the
    gripper, ratio 2.4).

    What the tiny CI model learns depends on the trainer's version (measured on this
    episode with three versions of soma_ros/training/train.py: grasped part +3.5, +32 and +147 mm,
    far part +0.1, +6 and +43 mm; three random models of the same config moved the
    grasped part by -4, -2 and +6 mm and the far part as much or more, in the same
    direction). The thresholds (grasped part > +1 mm and > 1.5x the far part's dz) test
    the direction and the locality of the response, not its size."""
    from benchmarks.bench_live import LiveProbe
    from soma_ros.live import load_live

    ckpt, scene, data = trained_run
    live = load_live(str(ckpt), str(scene))
    import json

    first_train = next(e["name"] for e in json.loads((data / "manifest.json").read_text())["episodes"]
                       if e["split"] == "train")
    vecs, k_close, tcp = recorded_grasp(live, data / first_train)
    lift = float(tcp[-1][2] - tcp[k_close][2])
    assert lift > 0.05, f"the recorded episode lifts by only {lift:.3f} m"
    x0 = live.snapshot()[0].means.double().numpy()
    dist = np.linalg.norm(x0 - tcp[k_close], axis=1)
    near, far = dist < 0.03, dist > 0.15
    assert near.sum() >= 20 and far.sum() >= 10, (near.sum(), far.sum())

    p = LiveProbe(ros_context, live.required_joints, cameras=())
    try:
        with sim_node(ros_env, (ckpt, scene), "render_rate_hz:=0.0", "splat_rate_hz:=10.0") as node:
            _started(p, node, vecs[0], key=("splats",))
            assert np.allclose(_means(p.last("splats")), x0, atol=1e-5)
            # one step per recorded pose, as recorded (30 FPS), whatever the node's step rate on a
            # busy machine: a node stepping slower than the stream would see the gripper jump
            p.play_stepped(vecs)
            # the first cloud after the lift's last pose (no long hold: a tiny model may keep drifting)
            cloud = p.wait_for("splats", timeout=30)
            assert cloud is not None
            x = _means(cloud)
            st = p.last_status()
            assert node.alive() and st.joint_states_rejected == 0
    finally:
        p.close()
    assert np.isfinite(x).all()
    dz_near = float((x[near, 2] - x0[near, 2]).mean())
    dz_far = float((x[far, 2] - x0[far, 2]).mean())
    print(f"\nlift {lift * 100:.1f} cm: grasped part dz {dz_near * 1e3:+.2f} mm, far part dz {dz_far * 1e3:+.2f} mm")
    assert dz_near > 1e-3, f"the grasped part did not rise: {dz_near * 1e3:+.2f} mm"
    assert dz_near > 1.5 * dz_far, f"grasped {dz_near * 1e3:+.2f} mm vs far {dz_far * 1e3:+.2f} mm"
