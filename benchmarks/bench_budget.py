"""Training budget: what a longer run buys, and what a schedule costs.

    python -m benchmarks.bench_budget curve --object rope --iterations 90 360 1000 --out runs/budget
    python -m benchmarks.bench_budget cost --object rope --out runs/budget \\
        --other schedule.stage1.length_start=2 schedule.stage1.length_growth=2

``curve``: the accuracy benchmark's ``full`` train config for the object (``--preset``, default
``tiny``) trained at each iteration count -- the same config, the epochs made longer
(``schedule.iters_per_epoch = N / epochs``), so the schedule's shape, the warm-up and the cosine
decay scale with it -- on the preset's reference-world dataset (``OUT/data/<object>_<preset>``,
generated or reused as ``soma bench accuracy`` does), then ``full``, ``prior_only`` (the kept
weights, network off) and ``static`` scored on the held-out episodes. Writes
``OUT/budget_<object>.csv`` (one row per iteration count and variant: held-out depth RMSE, Chamfer,
PSNR, the kept iteration, training wall and CPU seconds) and ``OUT/budget_<object>.png``. A complete
run in ``OUT/runs/<object>_<N>`` is reused.

``cost``: the CPU time of one training iteration (forward and backward of the rollout loss) of each
kind of rollout plan of the schedule (its stage, steps with gradients and supervised frames),
measured on one training episode (the median of ``--repeats``: stage 2's different window starts), times how often the schedule runs it: the training budget of the config, and of the config
with the ``--other`` overrides (e.g. the former growing stage-1 schedule), as a ratio. Validation,
scene set-up and evaluation are left out (the same for both). CPU seconds, not wall time, so that a
shared machine's load does not enter the ratio (it still slows both alike: caches and memory bandwidth).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

__all__ = ["main", "budget_curve", "schedule_cost"]

CURVE_COLUMNS = ["iterations", "variant", "rmse", "chamfer", "psnr", "kept_iteration", "train_wall_s", "train_cpu_s"]


def _setup(args):
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MUJOCO_GL", "egl")
    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))
    from soma_ros.evaluation.accuracy import _dataset, load_bench_config

    bench = load_bench_config(args.preset)
    out = Path(args.out)
    data = out / "data" / f"{args.object}_{bench.world.preset}"
    _dataset(bench, args.object, data, print, not args.quiet)
    return bench, out, data


def _config(bench, obj: str, iterations: Optional[int] = None, overrides: Optional[dict] = None):
    from soma_ros.evaluation.accuracy import variant_train_config
    from soma_ros.core.config import merge_config as _merge
    from soma_ros.training.config import load_train_config

    cfg = variant_train_config(bench, obj, "full")
    over = dict(overrides or {})
    if iterations is not None:
        ipe = max(1, round(iterations / cfg.schedule.epochs))
        over = _merge(over, {"schedule": {"iters_per_epoch": ipe},
                             "run": {"checkpoint_every": max(cfg.run.checkpoint_every, ipe)}})
    return load_train_config(_merge(cfg.to_dict(), over)) if over else cfg


def budget_curve(bench, obj: str, data: Path, out: Path, iterations: Sequence[int], progress: bool = True) -> list[dict]:
    """Train at each iteration count, score on the held-out episodes; returns the CSV rows."""
    import dataclasses

    from soma_ros.evaluation.baselines import StaticModel, load_model
    from soma_ros.evaluation.accuracy import _checkpoint_complete
    from soma_ros.evaluation.evaluate import EvalConfig, EvalContext, evaluate_models
    from soma_ros.core.scoring import EvalMetricsConfig
    from soma_ros.training.train import train

    rows = []
    for n in iterations:
        cfg = _config(bench, obj, n)
        cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, progress=progress))
        run = out / "runs" / f"{obj}_{n}"
        c0, t0 = time.process_time(), time.time()
        rec = run / "budget_train.json"
        if _checkpoint_complete(run) and rec.is_file():
            info = json.loads(rec.read_text())
        else:
            s = train(cfg, data, run, log=lambda m: print(f"[{obj} {n}] {m}", flush=True))
            info = {"kept_iteration": s["best_iteration"], "iterations": s["iterations"],
                    "train_wall_s": round(time.time() - t0, 1), "train_cpu_s": round(time.process_time() - c0, 1)}
            rec.write_text(json.dumps(info, indent=1))
        ctx = EvalContext.from_run(run, data)
        models = {"full": load_model(run / "checkpoint.pt"),
                  "prior_only": load_model(run / "checkpoint.pt", network=False), "static": StaticModel()}
        ecfg = EvalConfig(metrics=EvalMetricsConfig(with_lpips=False), contact_sheets=False, progress=progress)
        res = evaluate_models(models, ctx, "test", {v: run / "eval" / v for v in models}, ecfg,
                              log=lambda m: print(f"[{obj} {n}] {m}", flush=True))
        for v, r in res.items():
            rows.append({"iterations": cfg.schedule.total_iters, "variant": v,
                         **{m: r["mean"].get(m) for m in ("rmse", "chamfer", "psnr")},
                         "kept_iteration": info["kept_iteration"] if v != "static" else "",
                         "train_wall_s": info["train_wall_s"], "train_cpu_s": info["train_cpu_s"]})
    return rows


def _write_curve(out: Path, obj: str, rows: list[dict]) -> None:
    with open(out / f"budget_{obj}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, CURVE_COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8, 3.4), dpi=100)
    for ax, (m, label) in zip(axes, (("rmse", "held-out depth RMSE (m)"), ("chamfer", "held-out Chamfer (m)"))):
        for j, v in enumerate(dict.fromkeys(r["variant"] for r in rows)):
            pts = sorted((r["iterations"], r[m]) for r in rows if r["variant"] == v)
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", color=f"C{j}", label=v)
        ax.set_xscale("log")
        ax.set_xlabel("training iterations")
        ax.set_title(label, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    from soma_ros.core.machine import cpu_model

    fig.suptitle(f"{obj}: the same config at more iterations ({cpu_model()}, {os.cpu_count()} cores)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / f"budget_{obj}.png")
    plt.close(fig)


def schedule_cost(bench, obj: str, data: Path, out: Path, other: dict, repeats: int = 3) -> dict:
    """CPU seconds of one training iteration per distinct plan, times its count in the schedule."""
    import numpy as np
    import torch

    from soma_ros.core.config import load_object_config
    from soma_ros.core.robot import RobotModel
    from soma_ros.core.simulator import Simulator
    from soma_ros.data.dataset import load_dataset
    from soma_ros.training.train import (EpisodeStore, RolloutLoss, _set_up_scene, load_scene, plan_rollout, rest_reach,
                               split_validation, stage_at)

    res = {}
    for label, over in (("config", {}), ("other", other)):
        cfg = _config(bench, obj, None, over)
        train_refs, val_refs = split_validation(load_dataset(data, cfg.data.train_split), None, cfg.data)
        scene = out / "cost_scene"
        robot = RobotModel.from_config(cfg.robot, dtype=torch.float64)
        if not (scene / "scene.json").is_file():
            _set_up_scene(cfg, None, scene, train_refs, val_refs, robot, load_object_config(cfg.object),
                          cfg.model_config(), data, print)
        bundle, hier = load_scene(scene)
        torch.manual_seed(cfg.seed)
        sim = Simulator(cfg.model_config())
        sim.bind_hierarchy(hier)
        sim.train()
        loss_fn = RolloutLoss(sim, cfg, bundle)
        store = EpisodeStore(train_refs, robot, cfg, bundle, hier, out / "cost_cache")
        reach = rest_reach(sim)
        name = train_refs[0].name
        ep, init = store.episode(name), store.initial_splats(name)
        contact = store.contact(name, reach)
        counts: dict = {}
        plans: dict = {}  # up to `repeats` plans of each kind (stage, steps with gradients, supervised frames)
        for it in range(cfg.schedule.total_iters):
            info = stage_at(cfg, it // cfg.schedule.iters_per_epoch)
            plan = plan_rollout(info, name, ep.num_frames, np.random.default_rng([cfg.seed, it, 0]), contact,
                                cfg.schedule.stage1.sim_step)
            key = (info.stage, len(plan.frames), len(plan.loss_frames))
            counts[key] = counts.get(key, 0) + 1
            if len(plans.setdefault(key, [])) < repeats:
                plans[key].append(plan)
        per = {}
        for key, some in plans.items():
            times = []
            for plan in (some * repeats)[:repeats]:  # stage 2: different no-grad prefixes
                c0 = time.process_time()
                loss, _ = loss_fn(ep, init, plan)
                sim.zero_grad(set_to_none=True)
                loss.backward()
                times.append(time.process_time() - c0)
            per[key] = float(np.median(times))
        total = sum(per[k] * c for k, c in counts.items())
        res[label] = {"overrides": over, "iterations": cfg.schedule.total_iters, "cpu_s": total,
                      "plans": [{"stage": k[0], "grad_steps": k[1], "supervised": k[2], "count": c,
                                 "cpu_s_each": per[k]} for k, c in sorted(counts.items())]}
    res["ratio"] = res["config"]["cpu_s"] / res["other"]["cpu_s"]
    res["episode"] = name
    from soma_ros.core.machine import machine_info

    res["machine"] = {**machine_info(), "load": os.getloadavg()}
    return res


def _parse_overrides(items: Sequence[str]) -> dict:
    from soma_ros.commands.train import parse_overrides

    return parse_overrides(list(items)) if items else {}


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_budget", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("curve", "cost"):
        p = sub.add_parser(name)
        p.add_argument("--object", default="rope", choices=["rope", "cloth", "doll"])
        p.add_argument("--preset", default="tiny")
        p.add_argument("--out", required=True)
        p.add_argument("--quiet", action="store_true")
        if name == "curve":
            p.add_argument("--iterations", type=int, nargs="+", default=[90, 360, 1000])
        else:
            p.add_argument("--other", nargs="*", default=[], metavar="KEY=VALUE",
                           help="overrides of the schedule to compare with (soma train's KEY=VALUE form)")
            p.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    try:
        bench, out, data = _setup(args)
        if args.cmd == "curve":
            rows = budget_curve(bench, args.object, data, out, args.iterations, progress=not args.quiet)
            _write_curve(out, args.object, rows)
            for r in rows:
                print(f"{r['iterations']:>5} it  {r['variant']:<10}  rmse {r['rmse']:.4f} m  chamfer {r['chamfer']:.4f} m"
                      f"  kept it {r['kept_iteration']}")
            print(f"wrote {out / f'budget_{args.object}.csv'}, {out / f'budget_{args.object}.png'}")
        else:
            res = schedule_cost(bench, args.object, data, out, _parse_overrides(args.other), args.repeats)
            (out / f"cost_{args.object}.json").write_text(json.dumps(res, indent=1, default=str))
            for label in ("config", "other"):
                print(f"{label}: {res[label]['iterations']} iterations, {res[label]['cpu_s']:.1f} CPU s of rollouts")
            print(f"ratio config / other: {res['ratio']:.2f} (episode {res['episode']}; load {res['machine']['load']})")
    except (ValueError, FileNotFoundError, KeyError) as exc:
        print(f"bench_budget: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
