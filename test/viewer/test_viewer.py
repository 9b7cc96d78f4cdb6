"""`soma view`: the browser view of the twin, and its teleop.

The browser test starts ``soma view --run`` on a tiny trained model, loads the page in
headless Chromium (Debian's ``chromium`` package; skipped when it is not installed) and
compares screenshots of the scene with only the table and the camera frustums ("empty"),
with the splat layer added, and with the robot added: each must change the picture.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT

W, H = 960, 720
VIEW_W = int(0.62 * W)  # the 3D view; the control panel is on the right


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """A `soma train --config tiny` run of 2 iterations on 2 tiny rope episodes (conftest.train_tiny_run)."""
    from conftest import train_tiny_run

    root = tmp_path_factory.mktemp("view")
    train_tiny_run(root / "data", root / "run", episodes=2, frames=8)
    assert (root / "run" / "checkpoint.pt").is_file()
    return root / "run"


# --------------------------------------------------------------------------- teleop (no browser)
def test_jog_moves_the_tool_centre_through_ik_and_refuses_the_unreachable(tiny_run):
    from soma_ros.live import load_live
    from soma_ros.viewer.teleop import EndEffectorJog, JogRefused

    live = load_live(str(tiny_run / "checkpoint.pt"), str(tiny_run / "scene"))
    g = np.asarray(live.bundle.gravity, float)
    jog = EndEffectorJog(live.robot, live.base_to_sim.matrix(), live.required_joints, g)
    center = live.template.means.double().numpy().mean(0)
    start = center - 0.2 * g / np.linalg.norm(g)
    assert jog.home(start) < 2e-3
    np.testing.assert_allclose(jog.tcp(), start, atol=2e-3)
    vec = jog.jog([0.03, -0.02, 0.0])
    np.testing.assert_allclose(jog.tcp(), start + [0.03, -0.02, 0.0], atol=2e-3)
    # the joint vector drives the simulator's robot action: its control points are around the new target
    act = live.action(vec)
    np.testing.assert_allclose(act.control_points.double().numpy().mean(0), start + [0.03, -0.02, 0.0], atol=3e-3)
    assert act.gripper == pytest.approx(1.0)
    assert live.action(jog.set_gripper(False)).gripper == pytest.approx(0.0)
    q_before = jog.q.copy()
    with pytest.raises(JogRefused, match="cannot reach"):
        jog.jog([5.0, 0.0, 0.0])
    assert np.array_equal(jog.q, q_before)


# --------------------------------------------------------------------------- browser
def _start_view(run: Path, layers: str, env) -> tuple[subprocess.Popen, str, Path]:
    log = Path(run.parent / f"view_{layers.replace(',', '_')}.log")
    f = open(log, "w")
    proc = subprocess.Popen([sys.executable, "-m", "soma_ros.cli", "view", "--run", str(run), "--port", "0",
                             "--layers", layers, "--rate", "5", "--image-rate", "0", "--draw-rate", "2"],
                            stdout=f, stderr=subprocess.STDOUT, env=env, cwd=ROOT, process_group=0)
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        m = re.search(r"serving (http://\S+)", log.read_text())
        if m:
            return proc, m.group(1), log
        if proc.poll() is not None:
            break
        time.sleep(0.5)
    proc.kill()
    raise AssertionError(f"soma view did not start:\n{log.read_text()[-3000:]}")


def _shot(run: Path, layers: str, out: Path, env) -> np.ndarray:
    import cv2

    from soma_ros.viewer.screenshot import screenshot

    proc, url, log = _start_view(run, layers, env)
    try:
        # the 3D view (the control panel on the right shows the changing step count) drawn and still
        screenshot(url, out, wait_s=10.0, size=(W, H), stable_region=(0, 0, VIEW_W, H), timeout_s=240.0)
        assert proc.poll() is None, log.read_text()[-3000:]
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    img = cv2.imread(str(out))[:, :, ::-1]
    assert img.shape == (H, W, 3)
    return img[:, :VIEW_W]


def _differs(a: np.ndarray, b: np.ndarray) -> float:
    return float((np.abs(a.astype(int) - b.astype(int)).max(-1) > 24).mean())


@pytest.mark.skipif(shutil.which("chromium") is None, reason="needs Debian's chromium (apt-get install -y chromium)")
def test_browser_draws_the_splats_and_the_robot(tiny_run, tmp_path):
    """Each layer against the same scene without it (table and camera frustums only): the splat
    layer and the robot each change the picture."""
    import os

    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    empty = _shot(tiny_run, "cameras,table", tmp_path / "view_empty.png", env)
    splats = _shot(tiny_run, "splats,cameras,table", tmp_path / "view_splats.png", env)
    robot = _shot(tiny_run, "robot,cameras,table", tmp_path / "view_robot.png", env)
    d_splats, d_robot = _differs(splats, empty), _differs(robot, empty)
    print(f"pixels that change: splat layer {d_splats:.4f}, robot {d_robot:.4f} ({tmp_path})")
    assert d_splats > 5e-4, f"the splat layer draws nothing visible ({d_splats:.4%} of the view changes)"
    assert d_robot > 5e-3, f"the robot draws nothing visible ({d_robot:.4%} of the view changes)"
    # the splats are where the object is: their pixels are the rope's colour (red-orange), not grey
    changed = np.abs(splats.astype(int) - empty.astype(int)).max(-1) > 24
    px = splats[changed].astype(float)
    assert (px[:, 0] > px[:, 2] + 20).mean() > 0.5, px.mean(0)
    keep = os.environ.get("SOMA_VIEW_SCREENSHOT")
    if keep:  # the picture for a report: every layer
        _shot(tiny_run, "splats,robot,cameras,table", Path(keep), env)


# --------------------------------------------------------------------------- --node (no browser)
def test_node_mode_draws_what_a_running_node_publishes(ros_env, ros_context, untrained_run, monkeypatch):
    """`soma view --node`'s source in this process, a soma_sim_node in another, a probe playing the
    robot: the view gets the node's splats (in world), the robot from /robot_description posed by
    /joint_states, every camera with its simulated image at its TF pose, and the node's status."""
    from benchmarks.bench_live import LiveProbe, Poser
    from conftest import sim_node_args
    from soma_ros.live import load_live
    from soma_ros.nodes.testing import RosProcess
    from soma_ros.viewer.node import NodeSource
    from soma_ros.viewer.scene import TwinView

    monkeypatch.setenv("ROS_DOMAIN_ID", ros_env["ROS_DOMAIN_ID"])
    live = load_live(str(untrained_run[0]), str(untrained_run[1]))
    poser = Poser(live.robot, live.base_to_sim.matrix(), live.required_joints, live.bundle.gravity)
    hover = poser.solve((0.5, 0.02, 0.75 + 0.25))
    probe = LiveProbe(ros_context, live.required_joints, splats=False)
    node = RosProcess("soma_ros.nodes.sim_node", sim_node_args(*untrained_run), ros_env, name="sim_node_view")
    view = TwinView(port=0)
    src = NodeSource(view, draw_hz=5.0, image_hz=5.0)
    cams: dict = {}
    real_set_camera = view.set_camera
    view.set_camera = lambda name, *a, **k: (cams.__setitem__(name, (a, k)), real_set_camera(name, *a, **k))
    try:
        src.start()
        ok = probe.hold(hover, lambda: (view._splat_data is not None and view._robot is not None
                                        and {"cam_front", "cam_wrist"} <= set(cams)
                                        and "step rate" in view._status.content) or not node.alive(), 120.0)
        assert ok and node.alive(), (view._splat_data is None, view._robot, set(cams), node.output()[-3000:])
        means = view._splat_data[0]
        state, _, _ = live.snapshot()
        np.testing.assert_allclose(means, state.means.float().numpy(), atol=1e-5)  # soma_sim == world here
        (K, w, h, T), kw = cams["cam_wrist"]
        want = live.link_pose_sim(hover, live.cameras[1].mount_link) @ live.cameras[1].link_to_cam
        assert live.cameras[1].name == "cam_wrist"
        np.testing.assert_allclose(T, want, atol=1e-4)
        assert kw["sim_image"].shape == (h, w, 3) and kw["sim_image"].max() > 0
        assert "restarts" in view._status.content and "settles" in view._status.content
    finally:
        src.stop()
        view.close()
        node.stop()
        probe.close()


def test_bad_inputs_are_one_line_errors(tmp_path, capsys):
    from soma_ros.cli import main

    for args, what in ((["view", "--run", str(tmp_path / "nothing")], "no checkpoint at"),
                       (["view", "--resim", str(tmp_path)], "no rosbag2 at"),
                       (["view", "--node", "--layers", "splats,bogus"], "unknown layer(s) bogus"),
                       (["view", "--node", "--draw-rate", "0"], "--draw-rate must be > 0")):
        assert main(args) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("soma view: error:") and what in err[0], err


def test_a_robot_without_meshes_is_drawn_as_its_kinematic_chain():
    """The ARX X5's URDF ships without its mesh files: every link it cannot draw gets a bone from
    its parent's origin to its own, in the parent's frame, and a joint state poses the bones as FK
    poses the links (the end of the bone to ``link6`` is ``link6``'s origin)."""
    import torch

    from soma_ros.core.geometry import quat_to_rotmat
    from soma_ros.core.robot import RobotModel
    from soma_ros.core.robot_frames import RobotFrames
    from soma_ros.viewer.scene import TwinView

    urdf = RobotModel.from_config("arx5").config.urdf
    view = TwinView(port=0, layers=("robot",))
    try:
        base = np.eye(4)
        base[:3, 3] = [0.15, 0.0, 0.85]
        view.set_robot(urdf, base)
        frames = RobotFrames(urdf)
        chain = ["base_link", "link1", "link2", "link3", "link4", "link5"]
        assert set(chain) <= set(view._link_nodes), sorted(view._link_nodes)
        q = {"joint1": 0.4, "joint2": 1.0, "joint3": 0.8, "joint4": -0.3, "joint5": 0.5, "joint6": 0.2}
        view.set_joints(list(q), list(q.values()))
        poses = frames.link_poses(list(q), np.asarray(list(q.values())))
        parent = frames.urdf.joints["joint6"].parent
        node = view._link_nodes[parent]
        R = np.eye(4)
        R[:3, :3] = quat_to_rotmat(torch.as_tensor(np.asarray(node.wxyz, np.float64))).numpy()
        R[:3, 3] = node.position
        bone = np.asarray(view._bones[parent].points)  # [S, 2, 3] in the parent's frame
        assert any(np.allclose(seg[1], frames.urdf.joints["joint6"].origin_xyz, atol=1e-6) for seg in bone)
        end = R @ np.append(frames.urdf.joints["joint6"].origin_xyz, 1.0)
        np.testing.assert_allclose(end[:3], (base @ poses["link6"][0])[:3, 3], atol=1e-5)
    finally:
        view.close()
