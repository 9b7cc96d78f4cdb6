"""Switchable effects: each one moves the object's final state, never the robot's joints,
and is recorded only in the sidecar (not in the bag)."""

from __future__ import annotations

import json
import os
import sqlite3
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")

from soma_ros.world import EFFECTS, generate_dataset, load_world_config, parse_effects  # noqa: E402
from soma_ros.world.effect_report import measure_effects, read_states  # noqa: E402

#: (task, effects) measured per object: all effects on the rope (the cheapest object), dragged so
#: that the table matters too; one each on the cloth and the doll (the effect report covers the rest).
CASES = {"rope": ("drag", list(EFFECTS)), "cloth": ("fold", ["wind"]), "doll": ("lift", ["slip"])}


@pytest.fixture(scope="module")
def cfg():
    return load_world_config()


@pytest.fixture(scope="module")
def reports(cfg, tmp_path_factory):
    work = tmp_path_factory.mktemp("effects")
    return {obj: measure_effects(cfg, obj, "tiny", seed=0, index=0, effects=effs, task=task, work_dir=work)
            for obj, (task, effs) in CASES.items()}


@pytest.mark.parametrize("obj", list(CASES))
def test_each_effect_moves_the_object_but_not_the_robot(reports, obj):
    rep = reports[obj]
    assert rep["task"] == CASES[obj][0] and set(rep["effects"]) == set(CASES[obj][1])
    for eff, r in rep["effects"].items():
        print(f"{obj} {rep['task']} {eff}: final state moved {r['final_mean_mm']:.1f} mm mean, "
              f"{r['final_max_mm']:.1f} mm max; arm joints differ by {r['arm_max_diff_rad']:.1e} rad")
        assert r["final_mean_mm"] >= 1.0, (obj, eff, r)
        assert r["arm_max_diff_rad"] == 0.0, (obj, eff, r)


def test_baseline_is_deterministic(cfg, tmp_path):
    """Without this, 'the effect moved the object' could be run-to-run noise."""
    a = generate_dataset(cfg, "rope", "tiny", tmp_path / "a", episodes=1, seed=5, frames=20, progress=False)
    b = generate_dataset(cfg, "rope", "tiny", tmp_path / "b", episodes=1, seed=5, frames=20, progress=False)
    _, ja, pa = read_states(tmp_path / "a" / a["episodes"][0]["bag"])
    _, jb, pb = read_states(tmp_path / "b" / b["episodes"][0]["bag"])
    assert (ja == jb).all() and (pa == pb).all()


def test_effects_are_only_in_the_sidecar(cfg, tmp_path):
    on = generate_dataset(cfg, "rope", "tiny", tmp_path / "on", episodes=1, seed=1, frames=8, progress=False,
                          effects="wind,slip,stiff")
    off = generate_dataset(cfg, "rope", "tiny", tmp_path / "off", episodes=1, seed=1, frames=8, progress=False)
    name = on["episodes"][0]["name"]
    meta = json.loads((tmp_path / "on" / f"{name}.meta.json").read_text())
    assert set(meta["effects"]) == {"wind", "slip", "stiff"}
    assert meta["effects"]["wind"]["velocity"] == cfg.effects.wind.velocity
    assert meta["object_params"]["young_pa"] == pytest.approx(cfg.objects["rope"].young * cfg.effects.stiff.young_scale)
    meta_off = json.loads((tmp_path / "off" / f"{name}.meta.json").read_text())
    assert meta_off["effects"] == {}
    # The bags have the same topics, types and counts; nothing in them names an effect.
    md_on = (tmp_path / "on" / name / "metadata.yaml").read_text()
    md_off = (tmp_path / "off" / name / "metadata.yaml").read_text()
    strip = lambda s: [ln for ln in s.splitlines() if "duration" not in ln and "nanoseconds" not in ln and "size" not in ln]  # noqa: E731
    assert strip(md_on) == strip(md_off)
    db = sqlite3.connect(next((tmp_path / "on" / name).glob("*.db3")))
    tables = [r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")]
    text = md_on.lower() + " ".join(str(row) for t in tables if t != "messages" for row in db.execute(f"SELECT * FROM {t}"))
    db.close()
    for word in ("wind", "slip", "stiff", "young", "effect"):
        assert word not in text.lower()


def test_parse_effects():
    assert parse_effects("slip, wind,,slip") == ["wind", "slip"]
    assert parse_effects(None) == [] and parse_effects("") == []
    with pytest.raises(ValueError, match="unknown effect 'gravity'"):
        parse_effects("gravity")


def test_effects_yaml_names_every_effect():
    import yaml

    from soma_ros.paths import config_dir

    data = yaml.safe_load(Path(config_dir() / "world" / "effects.yaml").read_text())
    assert set(data) == set(EFFECTS)


def test_wind_onset_starts_the_wind_inside_the_carry(cfg, tmp_path):
    """A fan switched on mid-task (``effects.wind.onset``, a fraction of the carrying phase): the
    rope moves exactly as without wind until the onset, then differently; a wind without onset
    moves it from the first frame, while it still lies on the table; the onset is recorded in the
    sidecar; an onset outside [0, 1] is a clear error."""
    import dataclasses

    import numpy as np

    from soma_ros.world.config import WindConfig

    def episode(name, effects, onset):
        wind = dataclasses.replace(cfg.effects.wind, velocity=[0.0, 8.5, 0.0], onset=onset)
        c = dataclasses.replace(cfg, effects=dataclasses.replace(cfg.effects, wind=wind))
        man = generate_dataset(c, "rope", "tiny", tmp_path / name, episodes=1, seed=2, frames=24, progress=False,
                               effects=effects, task="drag")
        ep = man["episodes"][0]["name"]
        meta = json.loads((tmp_path / name / f"{ep}.meta.json").read_text())
        return read_states(tmp_path / name / ep)[2], meta

    still, _ = episode("none", None, None)
    always, _ = episode("always", "wind", None)
    late, meta = episode("late", "wind", 0.5)
    assert meta["effects"]["wind"]["onset"] == 0.5
    moved = lambda p: np.abs(p - still).reshape(len(p), -1).max(axis=1)  # noqa: E731  # [F] m
    first = lambda p: int(np.argmax(moved(p) > 0))  # noqa: E731
    print(f"first frame off the windless twin: wind from the start {first(always)}, onset 0.5 {first(late)}; "
          f"last frame {moved(always)[-1] * 1000:.1f} / {moved(late)[-1] * 1000:.1f} mm")
    assert first(always) == 1
    assert first(late) > 4 and moved(late)[-1] > 1e-4
    with pytest.raises(ValueError, match="onset"):
        WindConfig(onset=1.5)


def test_efforts_feel_a_heavier_rope_but_not_a_softer_one(cfg, tmp_path):
    """/joint_states effort carries the arm's external torques: the wrist force estimated from
    them (soma_ros.data.dataset, RobotModel.external_wrench) pulls down on the lifted rope. A 10x heavier
    rope moves as a 10x softer one does (a welded grasp on a position-controlled arm: only the
    ratio of weight to stiffness shapes the motion), which a camera cannot tell apart
    (docs/discrepancy.md); its pull on the wrist is 10x the softer one's. Effort noise
    never moves the motion."""
    import copy

    import numpy as np
    import torch

    from soma_ros.core.robot import RobotModel
    from soma_ros.data.dataset import prepare_episode

    c = copy.deepcopy(cfg)
    c.tasks["rope"] = ["lift"]
    c.motion.lift_height = [0.26, 0.32]
    c.effects.heavy.mass_scale = 10.0
    c.effects.stiff.young_scale = 0.1
    robot = RobotModel.from_config("panda", dtype=torch.float64)
    load, points = {}, {}
    for eff in ("none", "heavy", "stiff"):
        out = tmp_path / eff
        man = generate_dataset(c, "rope", "tiny", out, episodes=1, seed=0, frames=80, progress=False,
                               effects=None if eff == "none" else eff)
        ep = prepare_episode(out / man["episodes"][0]["bag"], robot)
        assert ep.wrist_force is not None and ep.wrist_force.shape == (80, 3)
        held = (ep.gripper < 0.5).numpy()
        held[:60] = False  # the rope is up from here on
        load[eff] = float(-ep.wrist_force[held, 2].mean())  # N, pulling down
        _, _, points[eff] = read_states(out / man["episodes"][0]["bag"])
    print({k: round(v, 3) for k, v in load.items()})
    gap = np.linalg.norm(points["heavy"] - points["stiff"], axis=-1).mean(axis=1)  # [F] m
    moved = np.linalg.norm(points["heavy"] - points["none"], axis=-1).mean(axis=1)
    print(f"heavy vs softer: {1e3 * gap.max():.2f} mm at most (heavy vs none {1e3 * moved.max():.1f} mm)")
    assert 0.15 < load["none"] < 0.6  # a 40 g rope, partly on the table
    assert gap.max() < 0.1 * moved.max()  # the same motion ...
    assert 8.0 < load["heavy"] / load["stiff"] < 12.5  # ... but about 10x the pull (11.0x measured)
    assert 0.5 < load["stiff"] / load["none"] < 1.2
    # the effort setting changes what is recorded, not what happens
    c.robot_config.effort = "none"
    man = generate_dataset(c, "rope", "tiny", tmp_path / "quiet", episodes=1, seed=0, frames=80, progress=False)
    _, _, pts = read_states(tmp_path / "quiet" / man["episodes"][0]["bag"])
    assert np.array_equal(pts, points["none"])
    ep = prepare_episode(tmp_path / "quiet" / man["episodes"][0]["bag"], robot)
    assert ep.wrist_force is None
