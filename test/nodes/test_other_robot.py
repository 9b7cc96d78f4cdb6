"""A robot other than the reference world's, end to end: bags -> soma train -> soma_sim_node.

The reference world records a Panda. ``tools/retarget_robot.py`` rewrites its bags as if an
ARX X5 (6 joints, the gripper an external value in metres, no finger links, its own URDF) had
moved its jaws the same way; the images, depth and masks stay as recorded. A model trained
on those bags with ``robot: arx5`` runs in ``soma_sim_node``, which follows the ARX's own
``/joint_states``: nothing in the chain may assume the Panda's joints, links or gripper.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import torch

from conftest import ROOT, recorded_grasp, sim_node_args
from soma_ros.nodes.testing import RosProcess

sys.path.insert(0, str(ROOT / "tools"))

START_TIMEOUT = 90.0
BASE = (0.15, 0.0, 0.85, 0.0)  # the ARX's base in the world (x, y, z, yaw deg): on a 10 cm riser, in reach


@pytest.fixture(scope="module")
def arx_run(tmp_path_factory):
    """(checkpoint, scene dir, retargeted dataset): 3 reference-world rope lifts retargeted to the
    ARX X5, and a `tiny` model trained on them for 2 iterations (the network starts at zero output,
    so the model is its priors: what the test checks is the chain, not what training adds)."""
    from retarget_robot import base_pose, retarget_bag
    from soma_ros.core.robot import RobotModel
    from soma_ros.training.config import load_train_config
    from soma_ros.training.train import train
    from soma_ros.world import generate_dataset, load_world_config

    root = tmp_path_factory.mktemp("arx")
    src, data, run = root / "panda", root / "arx", root / "run"
    generate_dataset(load_world_config(), "rope", "tiny", src, episodes=3, seed=0, task="lift", progress=False)
    panda = RobotModel.from_config("panda", dtype=torch.float64)
    arx = RobotModel.from_config("arx5", dtype=torch.float64)
    data.mkdir()
    manifest = json.loads((src / "manifest.json").read_text())
    for e in manifest["episodes"]:
        info = retarget_bag(src / e["name"], data / e["name"], panda, arx, base_pose(BASE))
        assert info["worst_mm"] < 1.0 and info["worst_deg"] < 0.5, (e["name"], info)
    (data / "manifest.json").write_text(json.dumps(manifest))
    cfg = load_train_config("tiny", {
        "robot": "arx5",
        "scene": {"photometric_iters": 3},
        "schedule": {"iters_per_epoch": 1, "stage1": {"epochs": 1, "stride": 2, "length_start": 2},
                     "stage2": {"epochs": 1, "window": 3}},
        "run": {"val_episodes": 1, "val_frame_stride": 3}})
    train(cfg, data, run, log=lambda *a, **k: None)
    return run / "checkpoint.pt", run / "scene", data


def test_a_model_trained_on_arx5_bags_follows_the_arx5_joint_states_in_the_node(ros_env, ros_context, arx_run):
    """The checkpoint names the ARX; the node takes its 6 joints and its gripper value, places
    the wrist camera on its ``eef_link`` and the base where the bags put it, and a recorded lift
    replayed as ARX joint states lifts the grasped part of the rope with the jaws (the model is
    its priors: the robot coupling's carry moves what the closed jaws hold with them)."""
    from benchmarks.bench_live import LiveProbe, cloud_means
    from soma_ros.live import load_live

    ckpt, scene, data = arx_run
    live = load_live(str(ckpt), str(scene))
    assert live.robot.config.name == "arx5"
    assert set(live.required_joints) == {"joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "gripper"}
    manifest = json.loads((data / "manifest.json").read_text())
    first_train = next(e["name"] for e in manifest["episodes"] if e["split"] == "train")
    vecs, k_close, tcp = recorded_grasp(live, data / first_train)
    lift = float(tcp[-1][2] - tcp[k_close][2])
    assert lift > 0.05, f"the recorded episode lifts by only {lift:.3f} m"
    x0 = live.snapshot()[0].means.double().numpy()
    dist = np.linalg.norm(x0 - tcp[k_close], axis=1)
    near = dist < 0.03
    assert near.sum() >= 20, near.sum()

    p = LiveProbe(ros_context, live.required_joints, cameras=("cam_wrist",), extra_joints=(), tf_static=True)
    node = RosProcess("soma_ros.nodes.sim_node",
                      sim_node_args(ckpt, scene, "-p", "render_rate_hz:=5.0", "-p", "splat_rate_hz:=10.0"),
                      ros_env, name="sim_node")
    try:
        ok = p.hold(vecs[0], lambda: (p.count.get(("splats",), 0) > 0 and p.count.get(("tf_static",), 0) > 0
                                      and p.count.get(("image", "cam_wrist"), 0) > 0) or not node.alive(),
                    START_TIMEOUT)
        assert ok and node.alive(), f"no splats / tf_static / image from soma_sim_node\n{node.output()[-4000:]}"
        edges = {(t.header.frame_id, t.child_frame_id) for t in p.last("tf_static").transforms}
        assert ("eef_link", "soma_sim/cam_wrist_optical") in edges and ("link6", "eef_link") in edges, edges
        assert any(child == "base_link" for _, child in edges), edges
        assert np.allclose(cloud_means(p.last("splats")), x0, atol=1e-5)
        p.play_stepped(vecs)
        cloud = p.wait_for("splats", timeout=30)  # the first cloud after the lift's last pose
        assert cloud is not None
        x = cloud_means(cloud)
        st = p.last_status()
        assert node.alive() and st.joint_states_rejected == 0, node.output()[-3000:]
    finally:
        p.close()
        rc = node.stop()
    assert rc in (0, -2), f"soma_sim_node exited with {rc}\n{node.output()[-4000:]}"
    assert np.isfinite(x).all()
    dz_near = float((x[near, 2] - x0[near, 2]).mean())
    print(f"\nARX X5 lift of {lift * 1e3:.0f} mm: grasped part dz {dz_near * 1e3:+.1f} mm")
    assert 0.5 * lift < dz_near < 1.5 * lift, f"the grasped part rose {dz_near * 1e3:+.1f} mm for a {lift * 1e3:.0f} mm lift"
