"""`soma train` end to end on a reference-world tiny rope dataset (grasp-and-lift episodes).

One training run (config/train/tiny_mlp.yaml, CPU: the free-form robot force module, which
starts knowing nothing about the robot, so what training adds is plain) is started as a
subprocess, killed
with SIGKILL after its second checkpoint and started again with the same command:

* (c) the second process resumes from the last checkpoint: iteration counter,
  weights (checksum) and log carry on;
* (a) the finished run's validation loss (a training-split episode no gradient step used,
  full-rate open-loop rollouts) is well below the untrained model's, and a rollout of the
  kept (best-by-validation) checkpoint on the held-out test episodes moves with the
  gripper: the splats the gripper closes on rise with it;
* (b) a 2-process `torchrun` run on CPU (DDP over gloo) trains, keeps the ranks'
  weights identical, and writes the same checkpoint format.

CI budget (2 cores): the training run takes about 3 minutes, the torchrun run and
the fixtures about a minute more.
"""

from __future__ import annotations

import csv
import math
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = Path(__file__).resolve().parents[2]
KILL_AFTER_ITERATION = 30  # two epochs of the tiny config: the second checkpoint


def _env() -> dict:
    env = dict(os.environ)
    env.update(PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MUJOCO_GL="egl", PYTHONUNBUFFERED="1")
    return env


@pytest.fixture(scope="module")
def lift_dataset(tmp_path_factory) -> Path:
    """8 tiny grasp-and-lift rope episodes (6 train / 2 test), 40 frames each; the tiny config
    validates on the last training episode (5 stepped on, 1 validation)."""
    from soma_ros.world import generate_dataset, load_world_config

    out = tmp_path_factory.mktemp("trainer") / "rope_lift"
    generate_dataset(load_world_config(), "rope", "tiny", out, episodes=8, seed=0, task="lift", progress=False)
    return out


def _read_state(run: Path):
    from soma_ros.training.train import TRAIN_STATE

    p = run / TRAIN_STATE
    if not p.is_file():
        return None
    try:
        return torch.load(p, map_location="cpu", weights_only=True)
    except Exception:  # being replaced right now: try again
        return None


@pytest.fixture(scope="module")
def trained_run(lift_dataset, tmp_path_factory) -> dict:
    """Train with `soma train --config tiny_mlp`, SIGKILL it after the checkpoint at iteration >= 30,
    rerun the same command to completion."""
    run = tmp_path_factory.mktemp("trainer") / "run"
    cmd = [sys.executable, "-m", "soma_ros.cli", "train", "--data", str(lift_dataset), "--config", "tiny_mlp",
           "--out", str(run), "--quiet"]
    t0 = time.time()
    p = subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    killed_state = None
    try:
        while time.time() - t0 < 900:
            if p.poll() is not None:
                break
            st = _read_state(run)
            if st is not None and int(st["iteration"]) >= KILL_AFTER_ITERATION:
                p.send_signal(signal.SIGKILL)
                break
            time.sleep(0.3)
    finally:
        if p.poll() is None:
            p.kill()
        first_out = p.communicate(timeout=60)[0]
    assert p.returncode == -signal.SIGKILL, f"the first run was not killed mid-way (rc {p.returncode}):\n{first_out[-3000:]}"
    killed_state = _read_state(run)
    assert killed_state is not None
    t1 = time.time()
    second = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=1200)
    assert second.returncode == 0, second.stdout[-3000:] + second.stderr[-3000:]
    return {"run": run, "killed_iteration": int(killed_state["iteration"]),
            "killed_checksum": float(killed_state["weights_checksum"]), "first_out": first_out,
            "second_out": second.stdout + second.stderr, "summary": json.loads((run / "summary.json").read_text()),
            "seconds_first": t1 - t0, "seconds_second": time.time() - t1}


# --------------------------------------------------------------------------- (c) resume
def test_resume_after_kill_continues_from_the_last_checkpoint(trained_run):
    run, k = trained_run["run"], trained_run["killed_iteration"]
    s = trained_run["summary"]
    assert KILL_AFTER_ITERATION <= k < s["total_iterations"]
    assert s["complete"] and s["iterations"] == s["total_iterations"]
    assert s["resumed_from"] == [k]
    # the second process started from the killed run's weights (same checksum) ...
    assert f"resuming from iteration {k} (weights checksum {trained_run['killed_checksum']:.6f})" in trained_run["second_out"]
    # ... and did only the remaining iterations: every training iteration is logged exactly once
    with open(run / "log.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    its = [int(r["iteration"]) for r in rows if r["kind"] == "train"]
    assert its == list(range(1, s["total_iterations"] + 1))
    val_its = [int(r["iteration"]) for r in rows if r["kind"] == "val"]
    assert val_its == sorted(set(val_its)) and val_its[0] == 0 and val_its[-1] == s["total_iterations"]
    from soma_ros.core.checkpoint import read_checkpoint

    last = read_checkpoint(run / "checkpoint_last.pt")["extra"]
    assert last["iteration"] == s["total_iterations"] and last["complete"] and last["resumed_from"] == [k]
    # checkpoint.pt keeps the weights of the best validation (run.keep: best), also across the resume
    kept = read_checkpoint(run / "checkpoint.pt")["extra"]
    assert kept["kept"] == "best" and kept["complete"] and kept["run_iteration"] == s["total_iterations"]
    best = min(s["val_history"], key=lambda h: h["val_loss"])
    assert kept["iteration"] == s["best_iteration"] == best["iteration"]
    assert kept["val_loss"] == pytest.approx(best["val_loss"]) == pytest.approx(s["best_val_loss"])


def test_validation_episodes_are_training_split_episodes(trained_run, lift_dataset):
    """Validation (which picks the kept checkpoint) uses training-split episodes that take no
    gradient step; the held-out test episodes are neither trained on nor used for selection."""
    from soma_ros.data.dataset import load_dataset

    run = trained_run["run"]
    s = trained_run["summary"]
    test_names = {r.name for r in load_dataset(lift_dataset, "test")}
    train_names = {r.name for r in load_dataset(lift_dataset, "train")}
    assert s["val_episodes"] and set(s["val_episodes"]) <= train_names
    assert not set(s["val_episodes"]) & set(s["train_episodes"])
    assert not (set(s["val_episodes"]) | set(s["train_episodes"])) & test_names
    with open(run / "log.csv", newline="") as f:
        stepped = {r["episode"] for r in csv.DictReader(f) if r["kind"] == "train"}
    assert stepped <= set(s["train_episodes"])


# --------------------------------------------------------------------------- (a) learning
def test_training_lowers_validation_loss_and_outputs(trained_run):
    run = trained_run["run"]
    s = trained_run["summary"]
    print(f"\ntiny run: {trained_run['seconds_first']:.0f} s until the kill + {trained_run['seconds_second']:.0f} s "
          f"resumed; val loss {s['val_loss_untrained']:.4f} (untrained) -> {s['val_loss']:.4f}; history "
          f"{json.dumps(s['val_history'])}")
    first, last = s["val_history"][0], s["val_history"][-1]
    assert first["iteration"] == 0 and last["iteration"] == s["total_iterations"]
    # the kept checkpoint (best validation; stage 2 can raise the validation loss again: measured
    # 0.146 after stage 1 -> 0.232 at the end on this dataset) is well below the untrained model's ...
    kept = min(s["val_history"], key=lambda h: h["val_loss"])
    assert kept["iteration"] > 0 and kept["val_loss"] < 0.75 * s["val_loss_untrained"], s["val_history"]
    # ... mostly because the predicted object is where the cameras see it (observed points are
    # closer); the paper's image term alone improves too, but less (the rope is 2-3 px wide in
    # the fixed cameras at 160x120: it only drops once the prediction is nearly pixel-exact)
    assert kept["points"] < 0.6 * first["points"], s["val_history"]
    assert kept["img"] < first["img"], s["val_history"]
    assert last["val_loss"] < first["val_loss"], s["val_history"]  # the latest weights learned too
    # outputs of a run
    for name in ("checkpoint.pt", "train_state.pt", "log.csv", "loss.png", "train_config.yaml", "scene/scene.json",
                 "scene/splats.ply", "scene/hierarchy.pt"):
        assert (run / name).is_file(), name
    assert (run / "loss.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _follow(sim, store, names, bundle):
    from soma_ros.training.train import gripper_follow, rollout_full

    out = []
    for name in names:
        ep = store.episode(name)
        states = rollout_full(sim, ep, store.initial_splats(name), bundle)
        f = gripper_follow(states, ep, torch.as_tensor(bundle.table_normal))
        assert f is not None and f["n_splats"] > 20 and f["gripper_rise"] > 0.08, f
        out.append(f)
    return out


def test_trained_model_follows_the_lift(trained_run, lift_dataset):
    """Roll the checkpoint out at the frame rate on the held-out lift episodes, as the live node
    would (checkpoint + scene bundle): the splats within 3 cm of the gripper when it closes rise
    with it; the untrained model's stay on the table."""
    from soma_ros.core.checkpoint import load_checkpoint
    from soma_ros.core.robot import RobotModel
    from soma_ros.core.simulator import Simulator
    from soma_ros.training.config import load_train_config
    from soma_ros.data.dataset import load_dataset
    from soma_ros.training.train import EpisodeStore, load_scene

    run = trained_run["run"]
    cfg = load_train_config(run / "train_config.yaml")
    bundle, hier = load_scene(run / "scene")
    robot = RobotModel.from_config(cfg.robot, dtype=torch.float64)
    refs = load_dataset(lift_dataset, "test")
    store = EpisodeStore(refs, robot, cfg, bundle, hier, run / "cache")
    names = [r.name for r in refs]
    sim = load_checkpoint(run / "checkpoint.pt").eval()
    torch.manual_seed(cfg.seed)
    untrained = Simulator(cfg.model_config())
    untrained.bind_hierarchy(hier)
    untrained.eval()
    trained_f = _follow(sim, store, names, bundle)
    untrained_f = _follow(untrained, store, names, bundle)
    print("\nfollow (splat rise / gripper rise): trained", [round(f["ratio"], 3) for f in trained_f],
          "untrained", [round(f["ratio"], 3) for f in untrained_f])
    for f in untrained_f:
        assert abs(f["ratio"]) < 0.1
    for f in trained_f:  # rises with the gripper (it overshoots in the hold phase: see the report)
        assert 0.5 < f["ratio"] < 2.5, f


def test_another_datasets_episode_of_the_source_name_starts_aligned_to_its_own_frame(trained_run, lift_dataset,
                                                                                       tmp_path):
    """The scene's G_0 is reconstructed from one training episode (``rope_000``) and used as that
    episode's initial state unaligned. An episode of the same name in another dataset (another world
    seed: a rope placed elsewhere) is a different rope: it must start from G_0 aligned to its own
    frame 0, as every other episode does, not from the training rope's place."""
    from soma_ros.core.robot import RobotModel
    from soma_ros.world import generate_dataset, load_world_config
    from soma_ros.training.config import load_train_config
    from soma_ros.data.dataset import load_dataset
    from soma_ros.training.train import EpisodeStore, load_scene

    run = trained_run["run"]
    cfg = load_train_config(run / "train_config.yaml")
    bundle, hier = load_scene(run / "scene")
    source = bundle.extra["source_episode"]
    robot = RobotModel.from_config(cfg.robot, dtype=torch.float64)
    own = EpisodeStore(load_dataset(lift_dataset), robot, cfg, bundle, hier, None)
    assert own.is_source(source)
    assert torch.equal(own.initial_splats(source).means, bundle.splats.means)

    other_dir = tmp_path / "other_seed"
    generate_dataset(load_world_config(), "rope", "tiny", other_dir, episodes=1, seed=7, task="lift", progress=False)
    refs = load_dataset(other_dir)
    assert [r.name for r in refs] == [source]
    other = EpisodeStore(refs, robot, cfg, bundle, hier, None)
    assert not other.is_source(source)
    pts, _ = other.episode(source).object_points([0])
    centre = pts.double().mean(0)
    g0_off = float((bundle.splats.means.double().mean(0) - centre).norm())
    init_off = float((other.initial_splats(source).means.double().mean(0) - centre).norm())
    print(f"\nseed-7 rope_000's frame-0 centre: {1000 * g0_off:.1f} mm from G_0's, {1000 * init_off:.1f} mm from its start")
    assert g0_off > 0.02  # the two ropes lie apart: the test can tell the two starts apart
    assert init_off < 0.25 * g0_off


def test_default_coupling_prior_follows_the_lift_before_any_training(trained_run, lift_dataset):
    """The default `tiny` model's robot effect is the physical coupling (control points drag the
    splats in reach towards their velocity, strongly with the gripper closed): with random
    network weights, never trained, the grasped splats already rise with the gripper on the
    held-out lifts, where the untrained free-form model's stay on the table (previous test)."""
    from soma_ros.core.robot import RobotModel
    from soma_ros.core.simulator import Simulator
    from soma_ros.training.config import load_train_config
    from soma_ros.data.dataset import load_dataset
    from soma_ros.training.train import EpisodeStore, load_scene

    run = trained_run["run"]
    cfg = load_train_config("tiny")
    robot_spec = next(e for e in cfg.model_config().effects if e.name == "robot")
    assert robot_spec.params["form"] == "coupling" and robot_spec.direct and not robot_spec.feature
    bundle, hier = load_scene(run / "scene")
    robot = RobotModel.from_config(cfg.robot, dtype=torch.float64)
    refs = load_dataset(lift_dataset, "test")
    store = EpisodeStore(refs, robot, cfg, bundle, hier, run / "cache_default")
    torch.manual_seed(cfg.seed)
    sim = Simulator(cfg.model_config())
    sim.bind_hierarchy(hier)
    sim.eval()
    f = _follow(sim, store, [r.name for r in refs], bundle)
    print("\nuntrained coupling follow:", [round(x["ratio"], 3) for x in f])
    for x in f:
        assert 0.5 < x["ratio"] < 2.0, x


# --------------------------------------------------------------------------- (b) torchrun
def test_torchrun_two_processes_on_cpu(trained_run, lift_dataset, tmp_path):
    from soma_ros.core.checkpoint import load_checkpoint, read_checkpoint

    run2 = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "soma_ros.cli", "train", "--data", str(lift_dataset), "--config", "tiny_mlp", "--out", str(run2),
           "--set", "schedule.iters_per_epoch=3", "--set", "schedule.stage1.epochs=1",
           "--set", "schedule.stage2.epochs=1", "--quiet"]
    p = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    s = json.loads((run2 / "summary.json").read_text())
    assert s["world_size"] == 2 and s["complete"] and s["iterations"] == 6
    ranks = [json.loads((run2 / "dist" / f"rank_{r}.json").read_text()) for r in (0, 1)]
    # DDP kept the replicas identical while each rank rolled out its own episodes
    assert ranks[0]["weights_checksum"] == ranks[1]["weights_checksum"]
    assert ranks[0]["episodes"] != ranks[1]["episodes"]
    single = read_checkpoint(trained_run["run"] / "checkpoint.pt")
    multi = read_checkpoint(run2 / "checkpoint.pt")
    assert multi["format"] == single["format"]
    assert set(multi["state_dict"]) == set(single["state_dict"])
    assert all(multi["state_dict"][k].shape == single["state_dict"][k].shape for k in single["state_dict"])
    assert multi["model_config"] == single["model_config"]
    assert multi["extra"]["world_size"] == 2 and multi["extra"]["run_iteration"] == 6
    sim = load_checkpoint(run2 / "checkpoint.pt")
    assert sim.hierarchy.sizes == load_checkpoint(trained_run["run"] / "checkpoint.pt").hierarchy.sizes


def test_torchrun_time_boxed_replicas_stop_at_the_same_iteration(lift_dataset, tmp_path):
    """``--max-minutes`` under DDP: rank 0's clock decides, so both replicas stop at the same
    iteration with the same weights."""
    run = tmp_path / "ddp_boxed"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "soma_ros.cli", "train", "--data", str(lift_dataset), "--config", "tiny_mlp", "--out", str(run),
           "--set", "schedule.iters_per_epoch=3", "--set", "schedule.stage1.epochs=1",
           "--set", "schedule.stage2.epochs=1", "--quiet", "--max-minutes", "1e-6"]
    p = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    s = json.loads((run / "summary.json").read_text())
    assert s["world_size"] == 2 and s["timed_out"] and not s["complete"] and s["iterations"] == 1
    ranks = [json.loads((run / "dist" / f"rank_{r}.json").read_text()) for r in (0, 1)]
    assert ranks[0]["weights_checksum"] == ranks[1]["weights_checksum"]


# --------------------------------------------------------------------------- units
def test_at_rest_prefix_carries_no_gradient(lift_dataset):
    """Steps before the gripper can touch the object are exact no-ops, so running them without
    gradients (what the trainer does) gives the same gradient as a full-gradient rollout (in
    float64; in float32 the full-gradient version carries ~1e-3 relative cancellation noise from
    the prefix steps, whose contributions cancel only mathematically)."""
    from soma_ros.core.robot import RobotModel
    from soma_ros.core.simulator import Simulator
    from soma_ros.training.config import load_train_config
    from soma_ros.data.dataset import load_dataset
    from soma_ros.scene.scene_setup import setup_scene
    from soma_ros.training.train import RolloutLoss, RolloutPlan, contact_frame, rest_reach

    cfg = load_train_config("tiny", {"scene": {"num_splats": 300, "photometric_iters": 0}})
    robot = RobotModel.from_config("panda", dtype=torch.float64)
    from soma_ros.data.dataset import prepare_episode

    ref = load_dataset(lift_dataset, "train")[0]
    ep = prepare_episode(ref.bag, robot, cfg.data)
    mc = cfg.model_config()
    setup = setup_scene(ep, cfg.scene, "rope", "panda", 0.05, mc.hierarchy.thresholds)
    torch.manual_seed(0)
    sim = Simulator(mc)
    sim.bind_hierarchy(setup.hierarchy)
    sim.to(dtype=torch.float64)
    c = contact_frame(ep, setup.bundle.splats, rest_reach(sim))
    assert 3 < c < ep.num_frames - 4, c
    frames = list(range(1, c + 4))
    sup = [f for f in frames if f >= c]
    loss_mod = RolloutLoss(sim, cfg, setup.bundle)
    grads = []
    for plan in (RolloutPlan(ref.name, 1, [], frames, sup),
                 RolloutPlan(ref.name, 1, frames[: c - 1], frames[c - 1:], sup)):
        sim.zero_grad()
        loss, _ = loss_mod(ep, setup.bundle.splats, plan)
        loss.backward()
        grads.append(torch.cat([p.grad.flatten() for p in sim.parameters() if p.grad is not None]))
    assert grads[0].abs().max() > 0
    rel = float((grads[0] - grads[1]).norm() / grads[0].norm())
    assert rel < 1e-9, rel


def test_a_turned_network_frame_reaches_the_rollout_and_leaves_the_priors_alone(lift_dataset):
    """``schedule.yaw_augment``: the plan's ``network_yaw`` reaches the simulator. With a non-zero
    network the loss changes with the turn; with the untrained (zero-output) network of ``tiny``
    the rollout is the physical terms alone, which no turn changes."""
    from soma_ros.core.robot import RobotModel
    from soma_ros.core.simulator import Simulator
    from soma_ros.data.dataset import load_dataset, prepare_episode
    from soma_ros.scene.scene_setup import setup_scene
    from soma_ros.training.config import ConfigError, load_train_config
    from soma_ros.training.train import RolloutLoss, RolloutPlan, contact_frame, rest_reach

    cfg = load_train_config("tiny", {"scene": {"num_splats": 300, "photometric_iters": 0},
                                     "schedule": {"yaw_augment": True}})
    with pytest.raises(ConfigError, match="yaw_augment"):
        load_train_config("tiny", {"schedule": {"yaw_augment": "yes"}})
    robot = RobotModel.from_config("panda")
    ref = load_dataset(lift_dataset, "train")[0]
    ep = prepare_episode(ref.bag, robot, cfg.data)
    losses = {}
    for scale in (0.0, 1.0):
        mc = cfg.model_config()
        mc.gnn.out_init_scale = scale
        setup = setup_scene(ep, cfg.scene, "rope", "panda", 0.05, mc.hierarchy.thresholds)
        torch.manual_seed(0)
        sim = Simulator(mc)
        sim.bind_hierarchy(setup.hierarchy)
        c = contact_frame(ep, setup.bundle.splats, rest_reach(sim))
        frames = list(range(c, c + 8))
        loss_mod = RolloutLoss(sim, cfg, setup.bundle)
        with torch.no_grad():
            for yaw in (0.0, 1.3):
                plan = RolloutPlan(ref.name, 1, list(range(1, c)), frames, frames[3::4], network_yaw=yaw)
                losses[scale, yaw] = float(loss_mod(ep, setup.bundle.splats, plan)[0])
    assert losses[0.0, 0.0] == losses[0.0, 1.3]
    assert abs(losses[1.0, 0.0] - losses[1.0, 1.3]) > 1e-6 * losses[1.0, 0.0], losses


def test_schedule_plans():
    import numpy as np

    from soma_ros.training.config import load_train_config
    from soma_ros.training.train import plan_rollout, stage_at

    tiny = load_train_config("tiny")  # whole-episode rollouts from the first iteration
    assert [stage_at(tiny, e).steps for e in range(tiny.schedule.stage1.epochs)] == [8] * 4
    p = plan_rollout(stage_at(tiny, 0), "e", 40, np.random.default_rng(0), contact=13, sim_step="frame")
    assert p.supervised == [16, 20, 24, 28, 32, 36] and p.frames == list(range(13, 37))  # capped by the episode
    cfg = load_train_config("tiny", {"schedule": {"stage1": {"length_start": 2, "length_growth": 2}}})
    rng = np.random.default_rng(0)
    i0 = stage_at(cfg, 0)
    assert (i0.stage, i0.stride, i0.steps) == (1, 4, 2)
    assert stage_at(cfg, 1).steps == 4
    p = plan_rollout(i0, "e", 40, rng, contact=13, sim_step="frame")
    assert p.stride == 1 and p.supervised == [16, 20] and p.prefix == list(range(1, 13)) and p.frames == list(range(13, 21))
    p = plan_rollout(i0, "e", 40, rng, contact=13, sim_step="stride")
    assert p.stride == 4 and p.prefix == [4, 8, 12] and p.frames == [16, 20]
    i2 = stage_at(cfg, cfg.schedule.stage1.epochs)
    assert (i2.stage, i2.stride, i2.steps) == (2, 1, 6)
    for _ in range(20):
        p = plan_rollout(i2, "e", 40, rng, contact=13)
        assert len(p.frames) == 6 and p.frames[-1] <= 39 and p.frames[-1] >= 13
        assert p.prefix == list(range(1, p.frames[0]))


def test_configs_and_cli_overrides():
    from soma_ros.commands.train import parse_overrides
    from soma_ros.training.config import ConfigError, load_train_config

    paper = load_train_config("paper")
    assert paper.model_config().gnn.latent == 128 and paper.scene.num_splats == 13000
    assert (paper.schedule.stage1.stride, paper.schedule.stage1.length_growth, paper.schedule.stage2.window) == (10, 3, 13)
    assert paper.optim.lr == 4e-4 and paper.optim.grad_clip == 1.0 and paper.loss.lam == 0.9
    assert paper.loss.points_weight == 0 and paper.loss.depth_weight == 0  # image-only, as the paper
    over = parse_overrides(["schedule.iters_per_epoch=3", "loss.lam=0.8", "data.cameras=[cam_front, cam_wrist]"])
    cfg = load_train_config("tiny", over)
    assert cfg.schedule.iters_per_epoch == 3 and cfg.loss.lam == 0.8 and cfg.data.cameras == ["cam_front", "cam_wrist"]
    with pytest.raises(ConfigError, match="loss.lamb: unknown key"):
        load_train_config("tiny", {"loss": {"lamb": 0.5}})
    with pytest.raises(ConfigError, match="schedule.stage1.sim_step"):
        load_train_config("tiny", {"schedule": {"stage1": {"sim_step": "sometimes"}}})
    with pytest.raises(ValueError, match="expected KEY=VALUE"):
        parse_overrides(["lam"])
    p = subprocess.run([sys.executable, "-m", "soma_ros.cli", "train", "--help"], capture_output=True, text=True,
                       env=_env(), timeout=120)
    assert p.returncode == 0 and "--data" in p.stdout and "torchrun" in p.stdout


def test_a_run_folders_config_with_a_removed_option_at_its_old_value_loads(tmp_path):
    """Older run folders' train_config.yaml store ``loss.silhouette_weight: 0.0`` and
    ``identify.then: []``; they load, and any other value of them is refused in one line."""
    import yaml

    from soma_ros.training.config import ConfigError, load_train_config

    d = load_train_config("tiny").to_dict()
    old = {**d, "loss": {**d["loss"], "silhouette_weight": 0.0}, "identify": {**d["identify"], "then": []}}
    path = tmp_path / "train_config.yaml"
    path.write_text(yaml.safe_dump(old))
    assert load_train_config(path).to_dict() == d
    for section, key, value in (("loss", "silhouette_weight", 0.5), ("identify", "then", [{"coefficient": "stretch"}])):
        path.write_text(yaml.safe_dump({**old, section: {**old[section], key: value}}))
        with pytest.raises(ConfigError, match=rf"^train_config.yaml: {section}\.{key}: this option was removed"):
            load_train_config(path)


def test_keep_best_points_keeps_the_lowest_validation_point_distance(lift_dataset, tmp_path):
    """``run.keep: best_points``: checkpoint.pt holds the weights of the validation with the lowest
    point distance (observed depth points to the nearest splat), which need not be the lowest loss,
    and a resume that changes the criterion starts the choice afresh instead of comparing a loss
    with a distance."""
    from soma_ros.core.checkpoint import read_checkpoint
    from soma_ros.training.config import ConfigError, load_train_config
    from soma_ros.training.train import train

    with pytest.raises(ConfigError, match="run.keep: one of best, best_points, best_score, last"):
        load_train_config("tiny", {"run": {"keep": "lowest"}})
    over = {"scene": {"photometric_iters": 3, "num_splats": 400},
            "schedule": {"iters_per_epoch": 1, "stage1": {"epochs": 3, "stride": 2, "length_start": 2},
                         "stage2": {"epochs": 1, "window": 3}},
            "optim": {"lr": 3e-2, "network": {"lr": None, "warmup_iters": 0}},  # big steps: validations that differ
            "run": {"val_episodes": 1, "val_frame_stride": 6, "keep": "best_points"}}
    run = tmp_path / "run"
    s = train(load_train_config("tiny", over), lift_dataset, run, log=lambda *a, **k: None)
    hist = s["val_history"]
    assert len(hist) == 5 and len({h["points"] for h in hist}) > 1, hist
    best = min(hist, key=lambda h: h["points"])
    kept = read_checkpoint(run / "checkpoint.pt")["extra"]
    assert s["kept"] == kept["kept"] == "best_points"
    assert kept["iteration"] == s["best_iteration"] == best["iteration"]
    assert s["kept_score"] == pytest.approx(best["points"]) and kept["val_loss"] == pytest.approx(best["val_loss"])
    # the same run resumed with keep: best -> chosen among the validations after the resume only
    over2 = dict(over, schedule=dict(over["schedule"], stage2={"epochs": 2, "window": 3}), run=dict(over["run"], keep="best"))
    logs: list = []
    s2 = train(load_train_config("tiny", over2), lift_dataset, run, log=lambda *a, **k: logs.append(a[0]))
    assert any("run.keep changed to best" in m for m in logs), logs
    assert s2["best_iteration"] == s2["total_iterations"] == 5 and s2["kept"] == "best"


def test_a_time_boxed_run_stops_validates_what_it_reached_and_resumes(lift_dataset, tmp_path):
    """``max_seconds`` (``soma train --max-minutes``): the loop stops at the first iteration past the
    limit, mid-epoch, validates and checkpoints the weights reached there; the same command without
    the limit resumes and completes the run."""
    from soma_ros.core.checkpoint import read_checkpoint
    from soma_ros.training.config import load_train_config
    from soma_ros.training.train import train

    over = {"scene": {"photometric_iters": 3, "num_splats": 400},
            "schedule": {"iters_per_epoch": 4, "stage1": {"epochs": 1, "stride": 2, "length_start": 2},
                         "stage2": {"epochs": 0, "window": 3}},
            "run": {"val_episodes": 1, "val_frame_stride": 6}}
    run = tmp_path / "run"
    logs: list = []
    s = train(load_train_config("tiny", over), lift_dataset, run, log=lambda *a, **k: logs.append(a[0]),
              max_seconds=1e-3)
    assert s["timed_out"] and not s["complete"] and s["iterations"] == 1 and s["total_iterations"] == 4
    assert [h["iteration"] for h in s["val_history"]] == [0, 1]
    assert any("stopped at iteration 1 of 4: the training time limit" in m for m in logs), logs
    assert read_checkpoint(run / "checkpoint_last.pt")["extra"]["iteration"] == 1
    done = train(load_train_config("tiny", over), lift_dataset, run, log=lambda *a, **k: None)
    assert done["complete"] and not done["timed_out"] and done["resumed_from"] == [1]
    assert [h["iteration"] for h in done["val_history"]] == [0, 1, 4]
    with pytest.raises(ValueError, match="max_seconds must be > 0"):
        train(load_train_config("tiny", over), lift_dataset, tmp_path / "r2", max_seconds=0)


def test_keep_best_score_selects_on_every_validation_task_and_writes_their_curves(lift_dataset, tmp_path):
    """``run.keep: best_score`` (the tiny config's): the kept weights are those of the lowest selection
    score -- image loss, scored-region depth and point distance per validation task relative to the
    untrained model (which scores exactly 1) --, and the run writes the per-task validation curves
    (``val_tasks.csv``, ``val_tasks.png``)."""
    from soma_ros.core.checkpoint import read_checkpoint
    from soma_ros.training.config import load_train_config
    from soma_ros.training.train import selection_score, train

    over = {"scene": {"photometric_iters": 3, "num_splats": 400},
            "schedule": {"iters_per_epoch": 1, "stage1": {"epochs": 3, "stride": 2, "length_start": 4},
                         "stage2": {"epochs": 1, "window": 3}},
            "optim": {"lr": 3e-2, "network": {"lr": 1e-2, "warmup_iters": 2}},
            "run": {"val_episodes": 1, "val_frame_stride": 6}}
    cfg = load_train_config("tiny", over)
    assert cfg.run.keep == "best_score" and cfg.run.score_terms == ["img", "depth", "points"]
    run = tmp_path / "run"
    s = train(cfg, lift_dataset, run, log=lambda *a, **k: None)
    hist = s["val_history"]
    assert len(hist) == 5 and hist[0]["score"] == 1.0 and len({h["score"] for h in hist}) > 1, hist
    ref = hist[0]["per_task"]
    assert list(ref) == ["lift"] and all(ref["lift"][k] > 0 for k in ("img", "depth", "points"))
    for h in hist:
        assert h["score"] == pytest.approx(selection_score(h["per_task"], ref, cfg.run.score_terms))
    best = min(hist, key=lambda h: h["score"])
    kept = read_checkpoint(run / "checkpoint.pt")["extra"]
    assert kept["kept"] == "best_score" and kept["iteration"] == s["best_iteration"] == best["iteration"]
    assert s["kept_score"] == pytest.approx(best["score"])
    with open(run / "val_tasks.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["iteration"]) for r in rows] == [h["iteration"] for h in hist] and {r["task"] for r in rows} == {"lift"}
    assert [float(r["score_terms_ratio"]) for r in rows] == pytest.approx([h["score"] for h in hist], rel=1e-5)
    assert float(rows[2]["depth"]) == pytest.approx(hist[2]["per_task"]["lift"]["depth"], rel=1e-5)
    assert (run / "val_tasks.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _identify_over(identify: dict) -> dict:
    """Overrides for a quick run on lift_dataset (3 photometric iterations, one stage-1 epoch, one
    validation episode) that identifies the prior's coefficients as ``identify`` says."""
    return {"scene": {"photometric_iters": 3, "num_splats": 400},
            "schedule": {"iters_per_epoch": 1, "stage1": {"epochs": 1, "stride": 2, "length_start": 2},
                         "stage2": {"epochs": 0, "window": 3}},
            "run": {"val_episodes": 1, "val_frame_stride": 6},
            "identify": identify}


def test_identify_sets_the_physics_priors_coefficient_with_the_lowest_score(lift_dataset, tmp_path):
    """``identify``: before training, the physics prior's bending compliance is set to each grid
    value, the untrained model is scored on training episodes (never the validation one) and the
    lowest validation-style score is kept; the run starts from it and records the table."""
    import math

    from soma_ros.core.checkpoint import read_checkpoint
    from soma_ros.training.config import ConfigError, load_train_config
    from soma_ros.training.train import train

    for bad in ({"coefficient": "youngs"}, {"values": [1e-8, -1.0]}, {"episodes": 0}, {"extend": -1},
                {"values": [1e-6], "extend": 2}):
        with pytest.raises(ConfigError, match="identify"):
            load_train_config("tiny_physics_newton", {"identify": bad})
    over = _identify_over({"coefficient": "bend", "values": [1e-7, 1e-5], "episodes": 2, "extend": 1})
    run = tmp_path / "run"
    logs: list = []
    s = train(load_train_config("tiny_physics_newton", over), lift_dataset, run, max_iterations=0,
              log=lambda *a, **k: logs.append(a[0]))
    ident = json.loads((run / "identify.json").read_text())
    assert s["identified"] == ident and ident["criterion"] == "val_loss"
    losses = [r["val_loss"] for r in ident["rows"]]
    assert losses[0] != losses[1]  # the stiffness changes the rollouts
    # the better of two values is always on the grid's edge: one more value beyond it (extend 1)
    edge = 1e-7 if losses[0] < losses[1] else 1e-5
    assert [r["value"] for r in ident["rows"]] == pytest.approx([1e-7, 1e-5, 1e-9 if edge == 1e-7 else 1e-3])
    assert [bool(r.get("extended")) for r in ident["rows"]] == [False, False, True]
    assert ident["chosen"] == ident["rows"][losses.index(min(losses))]["value"]
    assert not set(ident["episodes"]) & set(s["val_episodes"]) and len(ident["episodes"]) == 2
    sd = read_checkpoint(run / "checkpoint.pt")["state_dict"]
    assert float(sd["effects.terms.physics.log_bend"]) == pytest.approx(math.log(ident["chosen"]), rel=1e-6)
    assert not sd["gnn.decoder.net.2.weight"].any()  # the config's zero start: the untrained model is the prior alone
    assert any(m.startswith("identify: bend = ") for m in logs), logs
    with pytest.raises(ValueError, match="exactly one effect 'physics'"):
        train(load_train_config("tiny", {**over, "run": {"val_episodes": 1}}), lift_dataset, tmp_path / "run2",
              max_iterations=0, log=lambda *a, **k: None)


def test_identification_continues_a_grid_whose_best_value_is_on_its_edge():
    """``identify.extend``: the value beyond a grid's end continues that end's spacing (a ratio for
    compliances and damping, a difference for friction, never below 0); an interior value has none."""
    from soma_ros.training.config import beyond_edge

    assert beyond_edge([1.0, 3.0, 10.0, 30.0, 100.0], 100.0, True) == pytest.approx(100.0 * 100.0 / 30.0)
    assert beyond_edge([100.0, 1.0, 3.0], 1.0, True) == pytest.approx(1.0 / 3.0)
    assert beyond_edge([1.0, 3.0, 10.0], 3.0, True) is None
    assert beyond_edge([5.0], 5.0, True) is None
    assert beyond_edge([0.5, 1.0, 1.5], 1.5, False) == pytest.approx(2.0)
    assert beyond_edge([0.2, 0.5], 0.2, False) == 0.0 and beyond_edge([0.0, 0.5], 0.0, False) is None


def test_the_rod_config_identifies_the_rods_bending_on_a_reference_world_rope(lift_dataset, tmp_path):
    """``tiny_physics_rod``: the prior's nodes are a chain along the recorded rope's centre line and
    its bending compliance (the rod's, rho A / (4 EI)) is identified from the data like the pairs'."""
    from soma_ros.core.effects.physics import PhysicsPrior, build_layout
    from soma_ros.training.config import load_train_config
    from soma_ros.scene.files import load_scene
    from soma_ros.training.train import train

    over = _identify_over({"coefficient": "bend", "values": [1.0, 100.0], "episodes": 2})
    cfg = load_train_config("tiny_physics_rod", over)
    run = tmp_path / "run"
    s = train(cfg, lift_dataset, run, max_iterations=0, log=lambda *a, **k: None)
    losses = [r["val_loss"] for r in s["identified"]["rows"]]
    assert all(math.isfinite(v) for v in losses) and losses[0] != losses[1]  # the rod's stiffness changes the rollouts
    bundle, _ = load_scene(run / "scene")
    spec = next(e for e in cfg.model_config().effects if e.name == "physics")
    params = PhysicsPrior.Params(**spec.params)
    sc = bundle.scene_context()
    normal = torch.as_tensor(sc.plane_normal).double().reshape(3)
    lay = build_layout(bundle.splats.means.detach().double(), bundle.splats.mass.detach().double(), normal,
                       torch.tensor(float(sc.plane_offset)).double(), params)
    edges = (lay.rest[1:] - lay.rest[:-1]).norm(dim=-1)
    assert lay.tri is not None and lay.num_nodes >= 24 and float(edges.max()) < 3.0 * float(edges.median())


def test_the_grips_tilt_is_identified_when_the_rod_config_turns_it_on(lift_dataset, tmp_path):
    """``identify: {coefficient: tilt}`` sets the tilting grip's compliance (physics
    ``grip_tilt_compliance`` > 0) like the bending's; asked of a prior without it, a clear error."""
    from soma_ros.core.checkpoint import read_checkpoint
    from soma_ros.training.config import load_train_config
    from soma_ros.training.train import train

    base = load_train_config("tiny_physics_rod")
    effects = [dict(e) for e in base.model_overrides["effects"]]
    for e in effects:
        if e["name"] == "physics":
            e["grip_tilt_compliance"] = 0.01
    over = _identify_over({"coefficient": "tilt", "values": [0.002, 0.2], "episodes": 2})
    with pytest.raises(ValueError, match="no coefficient 'tilt'"):
        train(load_train_config("tiny_physics_rod", over), lift_dataset, tmp_path / "off", max_iterations=0,
              log=lambda *a, **k: None)
    run = tmp_path / "run"
    s = train(load_train_config("tiny_physics_rod", {**over, "model_overrides": {**base.model_overrides,
                                                                                  "effects": effects}}),
              lift_dataset, run, max_iterations=0, log=lambda *a, **k: None)
    losses = [r["val_loss"] for r in s["identified"]["rows"]]
    assert all(math.isfinite(v) for v in losses) and losses[0] != losses[1]  # the tilt changes the rollouts
    sd = read_checkpoint(run / "checkpoint.pt")["state_dict"]
    assert float(sd["effects.terms.physics.log_tilt"]) == pytest.approx(math.log(s["identified"]["chosen"]), rel=1e-6)


def test_a_non_finite_gradient_skips_the_step_and_keeps_the_weights():
    from soma_ros.training.train import clipped_step

    w = torch.nn.Parameter(torch.tensor([1.0, 2.0]))
    opt = torch.optim.Adam([w], lr=0.1)
    (w * torch.tensor([1.0, float("inf")])).sum().backward()
    gn, stepped = clipped_step(opt, [w], 1.0)
    assert not stepped and not math.isfinite(gn) and w.grad is None
    assert torch.equal(w.detach(), torch.tensor([1.0, 2.0]))  # untouched, and Adam's state too
    assert not opt.state
    (w * torch.tensor([3.0, 4.0])).sum().backward()
    gn, stepped = clipped_step(opt, [w], 1.0)
    assert stepped and gn == pytest.approx(5.0) and bool(torch.isfinite(w).all())
    assert float(w[0].detach()) < 1.0 and float(w[1].detach()) < 2.0


def test_divergence_guard_skips_then_rolls_back_then_stops():
    from soma_ros.training.train import DivergenceGuard

    g = DivergenceGuard(in_a_row=3, max_rollbacks=1, lr_factor=0.5)
    assert [g.update(i, s, True) for i, s in enumerate([True, False, False, True, False])] == \
        ["stepped", "skipped", "skipped", "stepped", "skipped"]  # a step taken resets the count
    assert g.update(5, False, True) == "skipped" and g.lr_scale == 1.0
    assert g.update(6, False, True) == "rollback" and g.rollbacks == [6] and g.lr_scale == 0.5
    assert g.skipped == [1, 2, 4, 5, 6]
    assert [g.update(i, False, True) for i in (7, 8)] == ["skipped", "skipped"]
    with pytest.raises(RuntimeError, match=r"iterations \[7, 8, 9\]: 3 non-finite .* after 1 rollback"):
        g.update(9, False, True)
    with pytest.raises(RuntimeError, match="no validated weights to go back to"):
        g2 = DivergenceGuard(in_a_row=1)
        g2.update(0, False, False)


def test_divergence_guard_carries_the_count_in_a_row_across_a_resume():
    """A run stopped after skipped steps and resumed goes on counting them: the saved skipped
    iterations that end just before the resume point, after the last rollback."""
    from soma_ros.training.train import DivergenceGuard

    g = DivergenceGuard(in_a_row=5, skipped=[3, 7, 8, 9]).resume_at(10)
    assert g.run == 3
    assert g.update(10, False, True) == "skipped" and g.update(11, False, True) == "rollback"
    assert DivergenceGuard(in_a_row=5, skipped=[3, 7, 8, 9]).resume_at(12).run == 0  # a step taken since
    assert DivergenceGuard(in_a_row=5, skipped=[5, 6, 7, 8, 9], rollbacks=[7]).resume_at(10).run == 2
    assert DivergenceGuard(in_a_row=5).resume_at(0).run == 0


def test_a_run_of_non_finite_steps_rolls_back_to_the_kept_weights(lift_dataset, tmp_path, monkeypatch):
    """Five steps in a row that cannot be taken (a fault injected where the gradient is checked):
    the loop goes back to the kept weights (here the untrained ones, the only validation so far)
    with fresh Adam moments and half the learning rate, and finishes; with no rollback allowed it
    stops with the error."""
    import soma_ros.training.train as T
    from soma_ros.training.config import ConfigError, load_train_config

    with pytest.raises(ConfigError, match="max_rollbacks"):
        load_train_config("tiny", {"optim": {"max_rollbacks": -1}})
    over = {"scene": {"photometric_iters": 3, "num_splats": 400},
            "schedule": {"iters_per_epoch": 1, "stage1": {"epochs": 7, "stride": 2, "length_start": 2},
                         "stage2": {"epochs": 0, "window": 3}},
            "run": {"val_episodes": 1, "val_frame_stride": 6, "val_every_epochs": 100}}
    real = T.clipped_step
    seen: list[dict] = []

    def faulty(opt, params, clip):
        params = list(params)
        k = len(seen)
        seen.append({"checksum": float(sum(p.detach().double().abs().sum() for p in params)),
                     "adam_state": len(opt.state), "lr": opt.param_groups[0]["lr"]})
        if 1 <= k <= 5:  # iterations 1-5
            opt.zero_grad(set_to_none=True)
            return float("inf"), False
        return real(opt, params, clip)

    monkeypatch.setattr(T, "clipped_step", faulty)
    cfg = load_train_config("tiny", over)
    logs: list = []
    s = T.train(cfg, lift_dataset, tmp_path / "run", log=lambda *a, **k: logs.append(a[0]))
    assert s["complete"] and s["skipped_iterations"] == [1, 2, 3, 4, 5] and s["rollbacks"] == [5]
    assert any("back to the weights of iteration 0" in m for m in logs), logs
    # the last lines say which weights checkpoint.pt holds, and whether training beat the untrained ones
    assert any(m.startswith(f"kept iteration {s['best_iteration']} in checkpoint.pt") for m in logs), logs
    assert any("did not improve on the untrained" in m for m in logs) == (s["best_iteration"] == 0), logs
    assert seen[1]["checksum"] != seen[0]["checksum"]  # iteration 0 stepped
    assert seen[6]["checksum"] == pytest.approx(seen[0]["checksum"], rel=1e-12)  # the untrained weights again
    assert seen[5]["adam_state"] > 0 and seen[6]["adam_state"] == 0
    assert seen[6]["lr"] == pytest.approx(0.5 * T.lr_at(cfg, 6, "network"))  # param_groups[0]: the network's
    assert seen[0]["lr"] == pytest.approx(T.lr_at(cfg, 0, "network"))
    seen.clear()
    cfg0 = load_train_config("tiny", {**over, "optim": {"max_rollbacks": 0}})
    with pytest.raises(RuntimeError, match=r"iterations \[1, 2, 3, 4, 5\]: 5 non-finite .* after 0 rollback"):
        T.train(cfg0, lift_dataset, tmp_path / "run0", log=lambda *a, **k: None)
