"""soma_sim_node against hostile or careless input: one test per bad-input class.

One node process (the untrained 2,000-splat run) serves the module. Each test sends
its bad reset while this process keeps publishing /joint_states, and checks the
refusal message, that the node kept stepping and kept taking /joint_states while the
reset was answered and after it, and that the running scene is unchanged. How fast
(refusal time, RSS, step rate under a flood) is measured in benchmarks/bench_fuzz.py.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import sim_node_args
from soma_ros.core.scene_guard import GENERIC_REFUSAL
from soma_ros.nodes.testing import RosProcess

SIM = "soma_ros.nodes.sim_node"
TABLE_Z = 0.75
START_TIMEOUT = 120.0


# --------------------------------------------------------------------------- the node
@pytest.fixture(scope="module")
def guarded(untrained_run, tmp_path_factory):
    """A running node with scene_dirs = [its scene folder, ALLOWED]; OUTSIDE is not allowed."""
    import rclpy
    from rclpy.context import Context

    from benchmarks.bench_live import LiveProbe, Poser
    from soma_ros.live import load_live
    from soma_ros.nodes.testing import ros_env, unique_domain_id

    root = tmp_path_factory.mktemp("guard")
    allowed, outside = root / "allowed", root / "outside"
    allowed.mkdir()
    outside.mkdir()
    live = load_live(str(untrained_run[0]), str(untrained_run[1]))
    poser = Poser(live.robot, live.base_to_sim.matrix(), live.required_joints, live.bundle.gravity)
    hover = poser.solve((0.5, 0.02, TABLE_Z + 0.25))
    domain = unique_domain_id()
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    args = sim_node_args(untrained_run[0], untrained_run[1], "-p", "render_rate_hz:=5.0", "-p", "splat_rate_hz:=5.0",
                         "-p", f"scene_dirs:=['{untrained_run[1]}', '{allowed}']")
    node = RosProcess(SIM, args, ros_env(domain), name="sim_node_guard")
    probe = LiveProbe(ctx, live.required_joints, cameras=("cam_front",))
    try:
        ok = probe.hold(hover, lambda: (probe.count.get(("splats",), 0) > 0 and probe.last_status() is not None)
                        or not node.alive(), START_TIMEOUT)
        assert ok and node.alive(), node.output()[-4000:]
        yield {"node": node, "probe": probe, "hover": hover, "allowed": allowed, "outside": outside,
               "run": untrained_run, "x0": live.bundle.splats.means.double().numpy(), "live": live}
    finally:
        probe.close()
        rc = node.stop()
        if ctx.ok():
            rclpy.shutdown(context=ctx)
    assert rc in (0, -2), f"soma_sim_node exited with {rc}\n{node.output()[-4000:]}"


def _accepted(st) -> int:
    return int(st.joint_states_received) - int(st.joint_states_rejected)


def _refused(g, reason: str, splats_msg=None, ply_path: str = "") -> str:
    """Send the reset while publishing /joint_states; check the refusal and that the node
    stepped and took joint states while it was answered and afterwards. Returns the message."""
    from benchmarks.bench_live import cloud_means
    from soma_msgs.srv import ResetScene

    p, hover = g["probe"], g["hover"]
    assert p.reset_client.wait_for_service(timeout_sec=30)
    st0 = p.last_status()
    req = ResetScene.Request()
    if splats_msg is not None:
        req.splats = splats_msg
    req.ply_path = ply_path
    fut = p.reset_client.call_async(req)
    assert p.hold(hover, fut.done, 60), "no answer from the reset service"
    resp = fut.result()
    assert not resp.success and resp.num_splats == 2000, resp.message
    assert resp.message.startswith("reset refused: ") and reason in resp.message, resp.message
    assert "\n" not in resp.message
    # during and after: steps go on and joint states are taken (more of both than before the call)
    assert p.hold(hover, lambda: p.last_status().step > st0.step + 3 and _accepted(p.last_status()) > _accepted(st0) + 3,
                  30), g["node"].output()[-3000:]
    st1 = p.last_status()
    assert st1.state == "running" and st1.num_splats == 2000
    n0 = p.count[("splats",)]
    assert p.hold(hover, lambda: p.count[("splats",)] > n0, 30)
    assert np.allclose(cloud_means(p.last("splats")), g["x0"], atol=1e-6)  # the running scene is the old one
    assert g["node"].alive()
    return resp.message


def _cloud(splats):
    from soma_ros.nodes.conversions import splats_to_cloud

    return splats_to_cloud(splats, "soma_sim")


def _variant(base, **kw):
    from soma_ros.nodes.testing import cloud_variant

    return cloud_variant(base, **kw)


def _rope(n=800, **kw):
    from soma_ros.core.scenes import synthetic_rope

    return synthetic_rope(n, center=(0.45, 0.05, TABLE_Z), seed=5, **kw)


# --------------------------------------------------------------------------- sizes
def test_a_lying_ply_header_is_refused_from_the_header(guarded):
    """A 385-byte ASCII PLY claiming 10^8 vertices, and a binary one claiming fewer than the
    limit but holding less data than announced: both refused before any vertex is read."""
    lying = guarded["allowed"] / "lying.ply"
    head = "ply\nformat ascii 1.0\nelement vertex 100000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    lying.write_text(head + "0 0 0\n" * ((385 - len(head)) // 6))
    msg = _refused(guarded, "announces 100000000 vertices, more than the limit of 200000", ply_path=str(lying))
    assert "lying.ply" in msg
    short = guarded["allowed"] / "short.ply"
    short.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 150000\nproperty float x\n"
                      b"property float y\nproperty float z\nend_header\n" + b"\0" * 1200)
    _refused(guarded, "truncated PLY: the header announces 1800000 bytes of data, the file holds 1200", ply_path=str(short))


def test_two_million_points_are_refused_from_the_message_size(guarded):
    """A real 2,000,000-point cloud (x, y, z: 24 MB): refused from width * height alone."""
    from sensor_msgs.msg import PointCloud2, PointField

    n = 2_000_000
    xyz = np.zeros((n, 3), np.float32)
    xyz[:, 0] = np.linspace(0.3, 0.7, n)
    xyz[:, 2] = TABLE_Z
    cloud = PointCloud2(height=1, width=n, point_step=12, row_step=12 * n, is_dense=True,
                        fields=[PointField(name=k, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                                for i, k in enumerate("xyz")], data=xyz.tobytes())
    _refused(guarded, "the splat cloud has 2000000 points, more than max_splats (200000)", splats_msg=cloud)


def test_a_1gb_file_is_refused_from_its_size(guarded):
    for name in ("huge.splat", "huge.ply"):
        big = guarded["allowed"] / name
        with open(big, "wb") as f:  # sparse: 1 GiB on paper, nothing on disk
            f.truncate(2**30)
        _refused(guarded, f"{name}: 1073741824 bytes, more than max_file_bytes (268435456)", ply_path=str(big))
        big.unlink()


def test_empty_cloud_and_field_count_mismatch_get_clear_answers(guarded):
    base = _cloud(_rope())
    _refused(guarded, "neither splats (0 points) nor a ply_path", splats_msg=_variant(base, width=0, data=b""))
    fields = list(base.fields)
    fields[0] = type(fields[0])(name="x", offset=0, datatype=7, count=3)
    _refused(guarded, "field 'x' must be FLOAT32 (7) with count 1, got datatype 7 count 3",
             splats_msg=_variant(base, fields=fields))


# --------------------------------------------------------------------------- layout and physics
def test_wrong_datatypes_are_refused(guarded):
    base = _cloud(_rope())
    for dt, name in ((2, "uint8"), (5, "int32")):
        fields = [type(f)(name=f.name, offset=f.offset, datatype=dt, count=1) for f in base.fields]
        _refused(guarded, f"field 'x' must be FLOAT32 (7) with count 1, got datatype {dt} count 1",
                 splats_msg=_variant(base, fields=fields))


def test_overlapping_fields_are_refused(guarded):
    base = _cloud(_rope())
    fields = [type(f)(name=f.name, offset=0, datatype=f.datatype, count=1) for f in base.fields]
    _refused(guarded, "overlap (bytes 0..4 and 0..4)", splats_msg=_variant(base, fields=fields))


def test_huge_splat_scales_are_refused(guarded):
    for scale in (0.1, 0.3):
        s = _rope()
        s.scales = s.scales * 0 + scale
        msg = _refused(guarded, "splats have a standard deviation above", splats_msg=_cloud(s))
        assert f"the largest is {scale:.3g} m" in msg


def test_a_text_file_named_splat_and_a_far_away_scene_are_refused(guarded):
    """Text bytes read as 32-byte records are absurd splats; a real rope 50 m away is too far."""
    txt = guarded["allowed"] / "notes.splat"
    txt.write_bytes((b"API_KEY=do-not-echo-this-line-0123456789abcdef\n" * 40)[:39 * 32])
    msg = _refused(guarded, "", ply_path=str(txt))
    assert any(k in msg for k in ("bounding radius", "centre", "standard deviation", "non-finite", "scales must be",
                                  "opacities")), msg
    assert "API_KEY" not in msg and "do-not-echo" not in msg
    far = _rope()
    far.means = far.means + 50.0
    _refused(guarded, "the scene's centre is", splats_msg=_cloud(far))


# --------------------------------------------------------------------------- where files may be read
def test_a_path_outside_scene_dirs_is_refused_like_a_missing_one(guarded):
    from soma_ros.core.ply import write_ply

    good = guarded["outside"] / "rope.ply"
    write_ply(good, _rope())  # a valid scene, only in the wrong place
    answers = {_refused(guarded, GENERIC_REFUSAL, ply_path=str(p)) for p in (
        good, guarded["outside"], guarded["outside"] / "missing.ply", guarded["allowed"] / "missing.ply",
        guarded["allowed"] / ".." / "outside" / "rope.ply", Path("/etc/splats.ply"))}
    assert answers == {"reset refused: " + GENERIC_REFUSAL}
    _refused(guarded, "ply_path must be an absolute path", ply_path="outside/rope.ply")


def test_a_symlink_escaping_scene_dirs_is_refused(guarded):
    link = guarded["allowed"] / "escape.ply"
    link.symlink_to("/etc/passwd")
    dir_link = guarded["allowed"] / "elsewhere"
    dir_link.symlink_to(guarded["outside"], target_is_directory=True)
    for p in (link, dir_link / "rope.ply"):
        msg = _refused(guarded, GENERIC_REFUSAL, ply_path=str(p))
        assert msg == "reset refused: " + GENERIC_REFUSAL and "root" not in msg


def test_etc_passwd_is_refused_without_a_word_about_it(guarded):
    for p in ("/etc/passwd", "/etc", "/etc/shadow", "/proc/self/environ"):
        assert _refused(guarded, GENERIC_REFUSAL, ply_path=p) == "reset refused: " + GENERIC_REFUSAL


def test_a_good_scene_inside_scene_dirs_and_inline_is_still_taken(guarded):
    """The checks refuse only what they should: a rope file in an allowed folder and an inline
    cloud are taken; then the original scene comes back from its bundle folder."""
    from benchmarks.bench_live import cloud_means
    from soma_ros.core.ply import write_ply

    p = guarded["probe"]
    s = _rope(1500)
    write_ply(guarded["allowed"] / "rope.ply", s)
    for kw in ({"ply_path": str(guarded["allowed"] / "rope.ply")}, {"splats_msg": _cloud(_rope(1200))}):
        resp = p.reset(**kw)
        assert resp.success, resp.message
    assert resp.num_splats == 1200
    resp = p.reset(ply_path=str(guarded["run"][1]))
    assert resp.success and resp.num_splats == 2000, resp.message
    assert p.hold(guarded["hover"], lambda: p.last("splats").width == 2000
                  and np.allclose(cloud_means(p.last("splats")), guarded["x0"], atol=1e-6), 30)


# --------------------------------------------------------------------------- corrupt model files, signals
def test_a_corrupt_checkpoint_stops_the_node_with_one_line_naming_it(untrained_run, tmp_path):
    """100 flipped bytes in the weights: the node does not start on them, and says why in one
    line that names the file (no traceback)."""
    from test_checkpoint import _flip_tensor_bytes

    bad = tmp_path / "checkpoint.pt"
    bad.write_bytes(Path(untrained_run[0]).read_bytes())
    _flip_tensor_bytes(bad)
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID="199")
    r = subprocess.run([sys.executable, "-m", SIM, *sim_node_args(bad, untrained_run[1])], env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 1, r.stdout[-2000:] + r.stderr[-2000:]
    errors = [ln for ln in r.stderr.splitlines() if "error" in ln]
    assert errors and str(bad) in errors[-1], r.stderr[-2000:]
    assert "SHA-256" in errors[-1] or "not a readable soma_ros checkpoint" in errors[-1], errors[-1]
    assert "Traceback" not in r.stderr + r.stdout


def test_sigterm_stops_a_node_with_a_reset_running_and_leaves_no_shared_memory(guarded, untrained_run):
    """A node busy with a large (valid) reset: a second reset is answered "busy", SIGTERM stops the
    process with status 0, and its shared-memory segments are gone. (Time to stop: bench_fuzz.)"""
    import rclpy
    from rclpy.context import Context
    from soma_msgs.srv import ResetScene

    from benchmarks.bench_live import LiveProbe
    from soma_ros.nodes.testing import ros_env, unique_domain_id

    domain = unique_domain_id()
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = RosProcess(SIM, sim_node_args(untrained_run[0], untrained_run[1], "-p", "render_rate_hz:=2.0"),
                      ros_env(domain), name="sim_node_sigterm")
    probe = LiveProbe(ctx, guarded["live"].required_joints, cameras=())
    try:
        assert probe.hold(guarded["hover"], lambda: probe.last_status() is not None or not node.alive(), START_TIMEOUT)
        mapped = {ln.split()[-1] for ln in open(f"/proc/{node.proc.pid}/maps") if "/dev/shm/" in ln}
        req = ResetScene.Request()
        req.splats = _cloud(_rope(150_000))  # valid, within limits: seconds of hierarchy building
        assert probe.reset_client.wait_for_service(timeout_sec=30)
        first = probe.reset_client.call_async(req)
        probe.spin_for(0.3)
        second = probe.reset_client.call_async(ResetScene.Request(ply_path=str(untrained_run[1])))
        assert probe.spin_until(second.done, 60)
        assert not first.done()  # still converting, checking and building the 150,000-splat hierarchy
        assert second.result().message == "reset refused: busy: another reset is still running"
        assert node.alive()
        os.killpg(node.proc.pid, signal.SIGTERM)
        rc = node.proc.wait(timeout=30)
        assert rc == 0, node.output()[-3000:]
        out = node.output()
        assert "did not stop" not in out and "Traceback" not in out, out[-3000:]
    finally:
        probe.close()
        node.stop()
        if ctx.ok():
            rclpy.shutdown(context=ctx)
    left = sorted(m for m in mapped if os.path.exists(m))
    # kept by design: LTTng-UST's per-user wait files and Fast DDS's per-port lock files, which
    # other participants on the machine share; the node's own segments must be gone
    assert not [m for m in left if not Path(m).name.startswith(("lttng-ust-wait-", "fastrtps_port", "sem.fastrtps_port"))], left


def test_the_guard_parameters_cannot_be_changed_at_run_time(guarded):
    """scene_dirs and the limits are read once at start and are read-only: a parameter client on
    the domain cannot widen them."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    p = guarded["probe"]
    client = AsyncParameterClient(p.node, "soma_sim_node")
    assert client.wait_for_services(timeout_sec=30)
    fut = client.set_parameters([Parameter("scene_dirs", value=["/"]), Parameter("max_splats", value=10**9)])
    assert p.spin_until(fut.done, 30)
    results = fut.result().results
    assert len(results) == 2 and not any(r.successful for r in results), results
    _refused(guarded, GENERIC_REFUSAL, ply_path="/etc/passwd")  # still the old folders
