"""Wall time of the discrepancy workflow's candidate fits, one after another vs in worker processes.

``rank_candidates`` (:mod:`soma_ros.discrepancy.workflow`) fits every candidate effect three times
(calibration on the reference, re-fit on the measured episodes, continued calibration): the
workflow's long part (about 75 min for 7 candidates on 80-frame rope episodes, one CPU core).
The candidates are independent, so ``jobs`` fits them in that many spawned worker processes.
This benchmark times :func:`soma_ros.discrepancy.workflow.rank_candidates` on a synthetic task for each
``--jobs`` value, checks that every value gives the same fits and ranking, and prints the
wall times and the speed-up over ``jobs=1`` with the machine named.

The task needs no bags, renderer or world: the ``tiny_physics`` model (the ``cpu`` network plus
the physics prior, so every library candidate acts) on synthetic ropes in the air; "measured"
episodes are rolled out by the same model plus a wind (``--wind``), the reference ones without;
observed points are the rolled-out splats with 3 mm of noise.

Usage: ``python -m benchmarks.discrepancy_jobs [--jobs 1 2] [--episodes 3] [--frames 13]
[--iters 6] [--json FILE]``
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import time

import torch

__all__ = ["wind_episodes", "synthetic_task", "time_ranking", "main"]


def wind_episodes(sim, scene, accel, seeds, split: str, frames: int = 13, splats: int = 300) -> list:
    """Synthetic observed episodes [EpisodeObs]: per seed a rope of ``splats`` in the air, rolled out
    ``frames`` long by ``sim`` plus a direct wind ``accel`` (m/s^2), every 4th frame observed as
    every 3rd splat with 3 mm of noise (as back-projected depth has)."""
    from soma_ros.core.scenes import synthetic_rope
    from soma_ros.discrepancy.workflow import EpisodeObs, _rollout

    world = copy.deepcopy(sim)
    world.add_effect({"name": "wind", "direct": True, "accel": list(accel)})
    keep = list(range(4, frames, 4))
    out = []
    for s in seeds:
        sp = synthetic_rope(splats, seed=s, center=(0.0, 0.0, 0.3))  # in the air: the wind moves it
        world.init_state(sp, scene)
        ob = EpisodeObs(f"e{s}", None, split, scene.dt, torch.full((frames, 4, 3), 3.0), torch.ones(frames), sp,
                        keep, [])
        g = torch.Generator().manual_seed(1000 + s)
        with torch.no_grad():
            ob.points = [st.means[::3] + 0.003 * torch.randn(st.means[::3].shape, generator=g)
                         for _, st in _rollout(world, ob, scene, keep)]
        out.append(ob)
    return out


def synthetic_task(episodes: int = 3, frames: int = 13, splats: int = 300, wind=(0.6, 0.0, 0.0)):
    """(model, fit, held-out, reference episodes, scene): the ``tiny_physics`` model bound to a
    synthetic rope; ``episodes`` of each kind (:func:`wind_episodes`), the reference without wind."""
    from soma_ros.core.scenes import synthetic_rope
    from soma_ros.core.simulator import SceneContext, Simulator
    from soma_ros.training.config import load_train_config

    torch.manual_seed(0)
    scene = SceneContext.table()
    sim = Simulator(load_train_config("tiny_physics").model_config()).eval()
    sim.init_state(synthetic_rope(splats, seed=1, center=(0.0, 0.0, 0.3)), scene)  # bind
    n = episodes
    ref = wind_episodes(sim, scene, (0.0, 0.0, 0.0), range(1, 1 + n), "train", frames, splats)
    fit = wind_episodes(sim, scene, wind, range(100, 100 + n), "train", frames, splats)
    held = wind_episodes(sim, scene, wind, range(200, 200 + n), "test", frames, splats)
    return sim, fit, held, ref, scene


def time_ranking(jobs: int, task, iters: int) -> dict:
    """Run rank_candidates with ``jobs`` workers on ``task``; wall time and the outcome."""
    from soma_ros.discrepancy.workflow import load_discrepancy_config, rank_candidates, residual_per_frame

    sim, fit, held, ref, scene = task
    cfg = load_discrepancy_config("physics", {"fit_iters": iters, "bootstrap": 300, "grid_episodes": 2})
    cfg = dataclasses.replace(cfg, jobs=jobs)
    base = [residual_per_frame(sim, o, scene) for o in held]
    t0 = time.perf_counter()
    named, ranking, _, fits, _, _ = rank_candidates(sim, fit, held, base, scene, cfg, lambda *a: None, ref)
    wall = time.perf_counter() - t0
    return dict(jobs=jobs, seconds=wall, named=named, candidates=len(fits),
                ranking=[(r["name"], r["explained_fraction"]) for r in ranking],
                parameters={k: v["parameters"] for k, v in fits.items()},
                candidate_seconds={k: v["seconds"] for k, v in fits.items()})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.discrepancy_jobs", description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, nargs="+", default=[1, 2], help="worker counts to time (first = baseline)")
    ap.add_argument("--episodes", type=int, default=3, help="fit, held-out and reference episodes each")
    ap.add_argument("--frames", type=int, default=13)
    ap.add_argument("--iters", type=int, default=6, help="Adam steps per fit")
    ap.add_argument("--json", default=None, metavar="FILE")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    from benchmarks.bench_core import machine_description

    machine = machine_description("cpu")
    print(machine, flush=True)
    task = synthetic_task(args.episodes, args.frames)
    rows = []
    for j in args.jobs:
        r = time_ranking(j, task, args.iters)
        rows.append(r)
        print(f"jobs {j}: {r['seconds']:.1f} s for {r['candidates']} candidates, named {r['named']}; per candidate "
              + ", ".join(f"{k} {v:.0f} s" for k, v in r["candidate_seconds"].items()), flush=True)
    same = all(r["ranking"] == rows[0]["ranking"] and r["parameters"] == rows[0]["parameters"] for r in rows)
    print(f"\n{'jobs':>4} {'wall s':>8} {'speed-up':>8}")
    for r in rows:
        print(f"{r['jobs']:>4} {r['seconds']:>8.1f} {rows[0]['seconds'] / r['seconds']:>7.2f}x")
    print(f"same fits and ranking for every jobs value: {'yes' if same else 'NO'} "
          f"({os.cpu_count()} cores; {args.episodes} episodes x 3, {args.frames} frames, {args.iters} Adam steps)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(machine=machine, cores=os.cpu_count(), rows=rows, same=same), f, indent=1)
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
