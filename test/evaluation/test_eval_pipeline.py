"""The evaluation harness end to end on a real (tiny) reference-world dataset:
`soma bench accuracy` with every variant on a CI-sized budget, the numbers it reports
cross-checked against independent computations, `soma eval` on the same run, reuse."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
import torch

from soma_ros.core import metrics as M
from soma_ros.core.render import render
from soma_ros.core.config import ConfigError
from soma_ros.evaluation.accuracy import BenchConfig, TrainSection, WorldSection, load_bench_config, run_bench, variant_train_config
from soma_ros.core.scoring import METRICS, chamfer_distance, complete_depth_maps, table_depth

torch.set_num_threads(1)

VARIANTS = ["full", "prior_only", "static", "state_only", "spring_mass", "img_only", "no_mrt"]


def _bench() -> BenchConfig:
    return BenchConfig(
        name="ci",
        objects=["rope"],
        variants=list(VARIANTS),
        world=WorldSection(preset="tiny", episodes=2, seed=3, frames=10),
        train=TrainSection(config="tiny", overrides={
            "scene": {"photometric_iters": 3},
            "schedule": {"iters_per_epoch": 1, "stage1": {"epochs": 1, "stride": 2, "length_start": 2},
                         "stage2": {"epochs": 1, "window": 3}},
            "run": {"val_episodes": 1, "val_frame_stride": 3},
        }),
        spring_mass={"iters": 2, "max_points": 300, "model": {"num_nodes": 30, "substeps": 6}},
        eval={"sheet_frames": 2, "video": True, "tile_width": 120},
    ).validate()


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    logs: list[str] = []
    res = run_bench(_bench(), out, progress=False, log=logs.append)
    return out, res, logs


def test_table_shape_and_files(bench_run):
    out, res, _ = bench_run
    table = json.loads((out / "table.json").read_text())
    assert list(table) == ["rope"]
    assert list(table["rope"]) == VARIANTS
    for v in VARIANTS:
        assert set(table["rope"][v]) == {"train", "test"}
        for split in ("train", "test"):
            row = table["rope"][v][split]
            assert list(row) == list(METRICS)
            assert all(isinstance(x, float) and math.isfinite(x) for x in row.values()), (v, split, row)
            assert row["psnr"] > 5 and 0 < row["ssim"] <= 1 and row["chamfer"] > 0 and row["rmse"] > 0
    md = (out / "table.md").read_text()
    assert "## rope" in md and "Gener. PSNR ↑" in md and "Resim. Chamfer (m) ↓" in md
    assert "RMSE: full" in md and "vs static" in md and "vs state_only" in md
    assert "full vs prior_only" in md and "| mean over tasks |" in md
    meta = json.loads((out / "bench.json").read_text())
    assert meta["objects"]["rope"]["episodes"] == {"train": 1, "test": 1}
    for v in VARIANTS:
        d = out / "eval" / "rope" / "test" / v
        assert (d / "metrics.json").is_file() and (d / "table.md").is_file()
        assert len(list((d / "sheets").glob("*.png"))) == 1 and len(list((d / "videos").glob("*.mp4"))) == 1
    assert (out / "runs" / "rope" / "spring_mass" / "spring_mass.pt").is_file()
    # the variants share the full run's scene (copied through the .ply writer: equal to float precision)
    from soma_ros.core.scene_bundle import SceneBundle

    ref = SceneBundle.load(out / "runs" / "rope" / "full" / "scene").splats
    for v in ("state_only", "img_only", "no_mrt"):
        sp = SceneBundle.load(out / "runs" / "rope" / v / "scene").splats
        torch.testing.assert_close(sp.means, ref.means, atol=1e-6, rtol=0)
        torch.testing.assert_close(sp.colors(), ref.colors(), atol=1e-5, rtol=0)


def test_variant_configs_differ_only_as_documented():
    b = _bench()
    full = variant_train_config(b, "rope", "full")
    img = variant_train_config(b, "rope", "img_only")
    nomrt = variant_train_config(b, "rope", "no_mrt")
    so = variant_train_config(b, "rope", "state_only")
    assert full.loss.momentum_weight > 0 and img.loss.momentum_weight == 0
    # img_only = the image loss alone: none of the 3D terms full adds on top of it
    assert full.loss.depth_weight > 0 and full.loss.depth_region == "scored"  # the tiny config's 3D term
    assert img.loss.points_weight == 0
    assert img.loss.depth_weight == 0
    assert img.loss.lam == full.loss.lam and img.loss.dssim_window == full.loss.dssim_window
    assert nomrt.schedule.stage1.epochs == 0 and nomrt.schedule.total_iters == full.schedule.total_iters
    eff = [e.name for e in so.model_config().effects]
    assert "robot" not in eff and "wind" in eff and "robot" in [e.name for e in full.model_config().effects]
    for c in (img, nomrt, so):
        assert c.data == full.data and c.scene == full.scene and c.optim == full.optim
    # per-object effect parameters (the tiny preset: no carry on cloth), in every variant that has the effect
    def robot(cfg):
        return [e for e in cfg.model_config().effects if e.name == "robot"][0].params
    tiny = load_bench_config("tiny")
    assert tiny.train.effect_params == {"cloth": {"robot": {"carry": 0.0}}}
    assert robot(variant_train_config(tiny, "rope", "full"))["carry"] == 0.5
    for v in ("full", "img_only", "no_mrt"):
        c = variant_train_config(tiny, "cloth", v)
        assert robot(c)["carry"] == 0.0 and robot(c)["form"] == "coupling"
        assert c.model_overrides["normalizer"] == {"mode": "fixed"}
    tiny.train.effect_params = {"cloth": {"tornado": {"x": 1}}}
    with pytest.raises(ConfigError, match="tornado"):
        variant_train_config(tiny, "cloth", "full")


def test_bench_never_selects_on_the_test_split():
    """Every learned variant validates (and so picks its kept checkpoint) on training-split
    episodes; a config that would validate on the scored test split is refused."""
    from soma_ros.evaluation.accuracy import _check_no_test_selection, load_bench_config
    from soma_ros.core.config import ConfigError

    from soma_ros.paths import config_dir

    presets = sorted(p.stem for p in (config_dir() / "eval").glob("*.yaml"))
    assert {"tiny", "tiny10", "paper", "tiny_mlp"} <= set(presets)
    for preset in presets:
        b = load_bench_config(preset)
        for v in ("full", "state_only", "img_only", "no_mrt"):
            c = variant_train_config(b, "rope", v)
            assert c.data.val_split is None and c.data.val_holdout >= 1 and c.run.keep in ("best", "best_score")
            _check_no_test_selection(c, v)
    bad = variant_train_config(_bench(), "rope", "full")
    bad.data.val_split = "test"
    with pytest.raises(ConfigError, match="test episodes"):
        _check_no_test_selection(bad, "full")


def test_static_numbers_match_an_independent_computation(bench_run):
    """Recompute the static baseline's scores of the held-out episode frame by frame with the core
    metrics and the ground-truth reader: frame alignment, masks and aggregation must agree."""
    from soma_ros.evaluation.evaluate import EvalContext
    from soma_ros.evaluation.ground_truth import read_ground_truth_points

    out, _, _ = bench_run
    res = json.loads((out / "eval" / "rope" / "test" / "static" / "metrics.json").read_text())
    (name, ep_res), = res["episodes"].items()
    ctx = EvalContext.from_run(out / "runs" / "rope" / "full", out / "data" / "rope_tiny")
    ep = ctx.store.episode(name)
    init = ctx.store.initial_splats(name)
    gt = read_ground_truth_points(ctx.store.refs[name].bag)
    assert gt.shape == (10, 25, 3)  # MuJoCo rope: 25 vertices
    psnrs, rmses, rmses_u, chamfers = [], [], [], []
    for t in range(1, ep.num_frames):
        cams = ep.cameras(t)
        r = render(init.means, init.covariances(), init.colors(), init.opacities, cams)
        pm, gm = M.apply_eval_masks(r.rgb, ep.rgb[t], ep.object_mask[t], ep.robot_mask[t])
        psnrs += M.psnr(pm, gm).tolist()
        tbl = table_depth(cams, ctx.scene.plane_normal, float(ctx.scene.plane_offset))
        pd, gd, region = complete_depth_maps(r.depth, r.alpha, ep.depth[t], ep.object_mask[t], ep.robot_mask[t], tbl,
                                             region="measured")
        rmses += M.depth_rmse(pd, gd, region).tolist()
        _, _, union = complete_depth_maps(r.depth, r.alpha, ep.depth[t], ep.object_mask[t], ep.robot_mask[t], tbl)
        rmses_u += M.depth_rmse(pd, gd, union).tolist()
        chamfers.append(chamfer_distance(init.means, torch.from_numpy(gt[t])))
    fin = [p for p in psnrs if math.isfinite(p)]
    assert ep_res["frames"] == ep.num_frames - 1
    assert ep_res["psnr"] == pytest.approx(float(np.mean(fin)), rel=1e-5)
    assert ep_res["rmse"] == pytest.approx(float(np.nanmean(rmses)), rel=1e-5)
    assert ep_res["rmse_union"] == pytest.approx(float(np.nanmean(rmses_u)), rel=1e-5)
    assert ep_res["chamfer"] == pytest.approx(float(np.mean(chamfers)), rel=1e-6)
    assert ep_res["per_frame"]["chamfer"] == pytest.approx(chamfers, rel=1e-6)
    # one episode per split: the split mean is that episode's mean
    assert res["mean"]["psnr"] == pytest.approx(ep_res["psnr"], rel=1e-9)


def test_soma_eval_cli_reproduces_the_bench_numbers(bench_run, tmp_path):
    from soma_ros.cli import main

    out, _, _ = bench_run
    run = out / "runs" / "rope" / "full"
    dst = tmp_path / "eval"
    rc = main(["eval", "--checkpoint", str(run), "--data", str(out / "data" / "rope_tiny"), "--split", "test",
               "--out", str(dst), "--quiet"])
    assert rc == 0
    got = json.loads((dst / "metrics.json").read_text())["mean"]
    ref = json.loads((out / "eval" / "rope" / "test" / "full" / "metrics.json").read_text())["mean"]
    for m in METRICS:
        assert got[m] == pytest.approx(ref[m], rel=1e-6, abs=1e-9), m
    # the spring-mass folder is a valid --checkpoint too; static needs --run
    rc = main(["eval", "--checkpoint", str(out / "runs" / "rope" / "spring_mass"), "--data",
               str(out / "data" / "rope_tiny"), "--split", "train", "--out", str(tmp_path / "sm"), "--quiet",
               "--no-lpips", "--no-sheets"])
    assert rc == 0 and "lpips" not in json.loads((tmp_path / "sm" / "metrics.json").read_text())["mean"]
    assert main(["eval", "--checkpoint", "static", "--data", str(out / "data" / "rope_tiny")]) == 2
    # --prior-only: the bench's prior_only row (full's kept checkpoint, network off)
    rc = main(["eval", "--checkpoint", str(run), "--prior-only", "--data", str(out / "data" / "rope_tiny"), "--split",
               "test", "--out", str(tmp_path / "prior"), "--quiet"])
    got = json.loads((tmp_path / "prior" / "metrics.json").read_text())
    ref = json.loads((out / "eval" / "rope" / "test" / "prior_only" / "metrics.json").read_text())
    assert rc == 0 and got["variant"] == "prior_only" and got["model"]["network"] is False
    for m in METRICS:
        assert got["mean"][m] == pytest.approx(ref["mean"][m], rel=1e-6, abs=1e-9), m


def test_rerun_reuses_finished_steps(bench_run):
    import dataclasses

    out, res, _ = bench_run
    logs: list[str] = []
    b = _bench()
    b = dataclasses.replace(b, variants=["full", "static", "spring_mass"],
                            eval={"contact_sheets": False, "metrics": {"with_lpips": False}})
    res2 = run_bench(b.validate(), out, progress=False, log=logs.append)
    text = "\n".join(logs)
    assert "data: reusing" in text and "full: reusing the complete run" in text and "spring_mass: reusing" in text
    assert "training" not in text and "fitting" not in text
    assert list(res2["table"]["rope"]) == ["full", "static", "spring_mass"]
    for v in ("full", "static", "spring_mass"):
        for split in ("train", "test"):
            for m in METRICS:
                if m == "lpips":
                    assert res2["table"]["rope"][v][split][m] is None
                    continue
                assert res2["table"]["rope"][v][split][m] == pytest.approx(res["table"]["rope"][v][split][m], rel=1e-6)


def test_parallel_objects_merge_their_rows_into_one_table(tmp_path):
    """Objects benchmarked by separate processes (``--jobs``) write into one folder: each write
    keeps the other processes' objects, and an object's own newest rows win."""
    from soma_ros.evaluation.accuracy import _write, load_bench_config

    bench = load_bench_config("tiny")
    row = lambda x: {"test": {m: x for m in METRICS}, "train": {m: x for m in METRICS}}  # noqa: E731
    _write(tmp_path, {"doll": {"full": row(1.0)}}, {"objects": {"doll": {"seconds": 10.0}}, "wall_seconds": 10.0}, bench)
    _write(tmp_path, {"rope": {"full": row(2.0)}}, {"objects": {"rope": {"seconds": 5.0}}, "wall_seconds": 5.0}, bench)
    # a process that started before doll was done holds doll's old rows: they must not win
    _write(tmp_path, {"rope": {"full": row(3.0)}, "doll": {"full": row(9.0)}},
           {"objects": {"rope": {"seconds": 6.0}, "doll": {"seconds": 99.0}}, "wall_seconds": 6.0}, bench, own=["rope"])
    table = json.loads((tmp_path / "table.json").read_text())
    meta = json.loads((tmp_path / "bench.json").read_text())
    assert sorted(table) == ["doll", "rope"]
    assert table["doll"]["full"]["test"]["rmse"] == 1.0 and table["rope"]["full"]["test"]["rmse"] == 3.0
    assert sorted(meta["objects"]) == ["doll", "rope"] and meta["wall_seconds"] == 10.0
    assert meta["objects"]["doll"]["seconds"] == 10.0 and meta["objects"]["rope"]["seconds"] == 6.0
    md = (tmp_path / "table.md").read_text()
    assert "## rope" in md and "## doll" in md and md.index("## rope") < md.index("## doll")  # canonical order
    # the parent of the children then records the whole run's wall time and job count, rows untouched
    from benchmarks.bench_accuracy import finish_parallel

    finish_parallel(tmp_path, "tiny", 42.0 * 60, 2)
    meta = json.loads((tmp_path / "bench.json").read_text())
    assert meta["wall_seconds"] == 2520.0 and meta["jobs"] == 2 and meta["command"]
    assert json.loads((tmp_path / "table.json").read_text()) == table
    assert "42.0 min wall time" in (tmp_path / "table.md").read_text()


def test_bench_cli_registration():
    import benchmarks.bench_accuracy as ba

    p = argparse.ArgumentParser()
    sub = p.add_subparsers()
    ba.register(sub)
    args = p.parse_args(["accuracy", "--preset", "tiny", "--objects", "rope", "--out", "x"])
    assert args.bench_func is ba.run and args.objects == "rope" and args.preset == "tiny"
    assert ba.main(["--preset", "nonexistent-preset", "--out", "x"]) == 1
    assert ba.main(["--preset", "tiny", "--jobs", "0", "--out", "x"]) == 1
