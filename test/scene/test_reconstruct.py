"""`soma reconstruct`: the real 4-view rope capture (fit on 3 views, score the 4th) and the
scene set-up from a reference-world bag (G_0, table plane, gravity, robot -> sim, hierarchy,
scene bundle), plus the per-episode alignment of G_0."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = Path(__file__).resolve().parents[2]


def _soma(*args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "soma_ros.cli", *args], capture_output=True, text=True, env=env,
                          timeout=timeout)


def test_real_capture_holdout(shared_dir, tmp_path):
    cap = shared_dir / "data" / "real_rope_4view"
    if not cap.is_dir():
        pytest.skip(f"{cap} not found")
    out = tmp_path / "cap"
    p = _soma("reconstruct", "--capture", str(cap), "--holdout-view", "3", "--iters", "20",
              "--resolution-scale", "0.25", "--out", str(out), "--quiet")
    assert p.returncode == 0, p.stderr[-3000:]
    m = json.loads((out / "metrics.json").read_text())
    assert m["holdout_view"] == 3 and m["train_views"] == [0, 1, 2]
    assert math.isfinite(m["psnr_holdout"]) and m["psnr_holdout"] > 14.0, m
    assert math.isfinite(m["psnr_holdout_init"]) and len(m["psnr_train_views"]) == 3
    assert all(0.0 <= r["alpha_iou"] <= 1.0 and 0.0 <= r["alpha_inside"] <= 1.0 for r in m["per_view"]), m["per_view"]
    assert (out / "holdout_compare.png").is_file() and (out / "splats.ply").is_file()
    bad = _soma("reconstruct", "--capture", str(cap), "--holdout-view", "7", "--out", str(tmp_path / "x"), "--quiet")
    assert bad.returncode == 2 and "out of range" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


@pytest.fixture(scope="module")
def two_episodes(tmp_path_factory) -> Path:
    from soma_ros.world import generate_dataset, load_world_config

    out = tmp_path_factory.mktemp("recon") / "rope"
    generate_dataset(load_world_config(), "rope", "tiny", out, episodes=2, seed=5, task="lift", frames=10,
                     progress=False)
    return out


def test_reconstruct_bag_writes_a_scene_bundle(two_episodes, tmp_path):
    from soma_ros.core.calibration import Sim3
    from soma_ros.core.hierarchy import Hierarchy
    from soma_ros.core.scene_bundle import SceneBundle

    out = tmp_path / "scene"
    p = _soma("reconstruct", "--bag", str(two_episodes / "rope_000"), "--config", "tiny", "--iters", "20",
              "--out", str(out), "--quiet")
    assert p.returncode == 0, p.stderr[-3000:]
    b = SceneBundle.load(out)
    n = len(b.splats)
    assert 300 < n <= 1500
    # gravity from the table plane and the sign rule; the table top of the reference world is z = 0.75
    g = np.asarray(b.gravity)
    assert abs(np.linalg.norm(g) - 9.81) < 1e-6 and math.degrees(math.acos(-g[2] / 9.81)) < 1.5
    assert b.table_normal[2] > 0.999 and abs(-b.table_offset / b.table_normal[2] - 0.75) < 0.003
    # the splats lie on the table, within the rope's thickness
    z = b.splats.means[:, 2]
    assert float(z.min()) > 0.745 and float(z.max()) < 0.775
    s3 = Sim3.from_dict(b.base_to_sim)
    assert np.allclose(s3.matrix()[:3, 3], [0.0, 0.0, 0.75], atol=1e-6) and abs(s3.s - 1) < 1e-9
    cams = {c.name: c for c in b.cameras}
    assert set(cams) == {"cam_front", "cam_side", "cam_wrist"}
    assert cams["cam_wrist"].mount_link == "panda_hand" and cams["cam_front"].cam_to_sim is not None
    h = Hierarchy.from_dict(torch.load(out / "hierarchy.pt", weights_only=True))
    assert h.sizes[0] == n and h.sizes[-1] == 1
    m = json.loads((out / "metrics.json").read_text())
    for cam, v in m["cameras"].items():
        assert v["psnr_masked"] > v["psnr_masked_unrefined"] - 0.5, (cam, v)
    assert m["cameras"]["cam_wrist"]["psnr_masked"] > 25.0
    # a user .ply instead of the fused depth
    p2 = _soma("reconstruct", "--bag", str(two_episodes / "rope_000"), "--ply", str(out / "splats.ply"),
               "--out", str(tmp_path / "scene_ply"), "--quiet")
    assert p2.returncode == 0, p2.stderr[-3000:]
    assert len(SceneBundle.load(tmp_path / "scene_ply").splats) == n


def test_align_splats_moves_g0_onto_another_episode(two_episodes):
    """G_0 of episode 0 aligned to episode 1's first frame lies on episode 1's object points;
    the non-rigid stage does not do worse than the rigid one."""
    from soma_ros.core.robot import RobotModel
    from soma_ros.training.config import load_train_config
    from soma_ros.data.dataset import load_dataset, prepare_episode
    from soma_ros.scene.scene_setup import align_splats, setup_scene

    cfg = load_train_config("tiny", {"scene": {"photometric_iters": 0}})
    robot = RobotModel.from_config("panda", dtype=torch.float64)
    refs = load_dataset(two_episodes)
    e0, e1 = (prepare_episode(r.bag, robot, cfg.data) for r in refs)
    setup = setup_scene(e0, cfg.scene, "rope", "panda", 0.05, [0.02, 0.2])
    g0 = setup.bundle.splats
    tgt, _ = e1.object_points([0])
    before = torch.cdist(tgt, g0.means).min(1).values.mean()
    moved, info = align_splats(g0, tgt, setup.bundle.table_normal, cfg.scene, setup.hierarchy.parents[0])
    after = torch.cdist(tgt, moved.means).min(1).values.mean()
    assert len(moved) == len(g0) and torch.equal(moved.sh_dc, g0.sh_dc) and torch.equal(moved.mass, g0.mass)
    assert float(after) < 0.006 and float(after) < float(before)
    assert info["rms_nonrigid"] <= info["rms_rigid"] + 1e-4


def test_setup_fit_uses_depth_and_bounds_anisotropy(two_episodes):
    """The set-up's photometric fit has the episode's depth in its loss, and
    ``photometric_aniso_reg`` keeps the fitted splats rounder than the unregularised fit."""
    from soma_ros.core.robot import RobotModel
    from soma_ros.data.dataset import load_dataset, prepare_episode
    from soma_ros.scene.scene_setup import setup_scene
    from soma_ros.training.config import load_train_config

    robot = RobotModel.from_config("panda", dtype=torch.float64)
    ep = prepare_episode(load_dataset(two_episodes)[0].bag, robot, load_train_config("tiny").data)
    ratios = {}
    for reg in (0.0, 1.0):
        cfg = load_train_config("tiny", {"scene": {"photometric_iters": 30, "photometric_aniso_reg": reg,
                                                   "photometric_max_aniso": 1.0}})
        setup = setup_scene(ep, cfg.scene, "rope", "panda", 0.05, [0.02, 0.2])
        hist = setup.info["photometric_history"]
        assert all("depth" in h and math.isfinite(h["depth"]) for h in hist), hist[-1]
        s = setup.bundle.splats.scales
        ratios[reg] = float((s.max(1).values / s.min(1).values).median())
    assert ratios[1.0] < ratios[0.0] and ratios[1.0] < 1.2, ratios
