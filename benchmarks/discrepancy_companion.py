"""How much of a hidden effect's displacement a physics twin's response explains (issue #8 study).

    python -m benchmarks.discrepancy_companion --object cloth --effect wind --term wind \\
        --values "0,4,0;0,8,0;0,16,0" --form pressure --data-dir DIR

The reference world records an effect-free dataset and its twin with one effect switched on
(same seed: same initial states and robot actions; ``benchmarks.discrepancy``'s generator and
effect magnitudes). The world's effect displacement per episode is ``D = x_effect - x_none``
on the evaluation-only ground-truth vertices ([E, T, M, 3]). The companion
(:mod:`benchmarks.companion`) simulates every episode from the same initial vertices and
actions, nominal and with its term ``--term`` at each value of ``--values`` (one value shared
by all episodes, as the workflow would fit), and the differential ``Dc`` is carried to the
vertices. Printed per value: ``explained = 1 - sum |D - Dc|^2 / sum |D|^2`` over all episodes
and per task (1 = the twin predicts the effect exactly, 0 = no better than leaving it out,
< 0 = worse), and the mean |Dc|; then an upper bound with each episode at its own best value
of the grid (or 0); before the table: the companion's nominal error against the
effect-free ground truth and the mean |D|.

``--term all`` with a list of effects prints the matrix effect x term (every term over a generic
grid, :data:`GRIDS`; the value chosen on two thirds of each task's episodes, the explained fraction
scored on the other third): does the right term win? And for each winner, the most such a channel
could do for the held-out episodes' gap: the Chamfer and vertex RMS to the effect's ground truth of a nominal model that is
exactly the effect-free ground truth, without and with the twin's differential.

``--calibrate N`` first fits the companion's nominal configuration to the effect-free episodes
(random search, :data:`SEARCH_SPACE`): a twin closer to the world's nominal motion.

This is the measurement that decides whether an effect channel built on such a twin could
shrink the discrepancy benchmark's gap by half (that needs explained >~ 0.75).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


def _values(text: str) -> list[list[float]]:
    out = []
    for v in text.split(";"):
        v = v.strip()
        if not v:
            continue
        try:
            out.append([float(x) for x in v.split(",")])
        except ValueError:
            raise SystemExit(f"benchmarks.discrepancy_companion: error: bad value {v!r} (numbers, ',' inside a "
                             f"vector, ';' between values)") from None
    if not out:
        raise SystemExit("benchmarks.discrepancy_companion: error: --values is empty")
    return out


def ground_truth(dataset: Path) -> dict:
    """Cached ground-truth vertices [E, T, M, 3], control points [E, T, P, 3] and gripper [E, T]
    (sim frame = the world frame of the reference world), dt, tasks and names of a dataset."""
    import torch

    cache = dataset / "companion_gt.npz"
    if cache.is_file():
        z = np.load(cache)
        return {k: z[k] for k in z.files}
    from soma_ros.core.robot import RobotModel
    from trainer.config import load_train_config
    from trainer.dataset import load_dataset, prepare_episode
    from trainer.evaluate_gt import read_ground_truth_points

    cfg = load_train_config("tiny")
    robot = RobotModel.from_config(cfg.robot, dtype=torch.float64)
    gt, cp, grip, tasks, names, dt = [], [], [], [], [], None
    for ref in load_dataset(dataset):
        ep = prepare_episode(ref.bag, robot, cfg)
        pts = read_ground_truth_points(ref.bag, stamps_ns=[int(s) for s in ep.stamps_ns.tolist()])
        gt.append(np.asarray(pts, np.float32))
        cp.append(ep.control_points.float().numpy())
        grip.append(ep.gripper.float().numpy())
        tasks.append(str(ref.task))
        names.append(ref.name)
        dt = ep.dt
    out = {"gt": np.stack(gt), "cp": np.stack(cp), "grip": np.stack(grip), "dt": np.float64(dt),
           "tasks": np.array(tasks), "names": np.array(names)}
    np.savez(cache, **out)
    return out


#: the random search of ``--calibrate``: CompanionConfig fields and their candidate values (lists) or
#: log10 ranges (tuples)
SEARCH_SPACE = {
    "num_nodes": [32, 48, 64, 96, 128], "bend_radius_factor": [4, 6, 8, 12, 16], "bend_neighbors": [4, 8, 12, 16],
    "attach_radius": [0.01, 0.015, 0.02, 0.03, 0.04, 0.06], "contact_offset_max": [0.0, 0.005, 0.01, 0.02],
    "carry_neighbors": [2, 4, 8], "bend_compliance": (-7.0, -2.0), "stretch_compliance": (-9.0, -5.0),
    "drag": (-1.0, 1.0), "friction": [0.1, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5],
}


#: ``--term all``: every term over a generic grid (set before looking at any effect's size): wind
#: 1-16 m/s^2 in the four horizontal directions, friction changes both ways, slips and scales on a
#: doubling ladder
GRIDS = {
    "wind": ";".join(f"{a * m:g},{b * m:g},0" for a, b in ((1, 0), (-1, 0), (0, 1), (0, -1)) for m in (1, 2, 4, 8, 16)),
    "table_friction": "-0.45;-0.3;-0.15;0.3;0.6",
    "gripper_slip": "1;2;3;4;6;8",
    "mass_scale": "0.5;1;2;4",
    "stiffness_scale": "-0.5;1;3;9",
    "quadratic_drag": "0.5;1;2;4",
    "linear_drag": "0.5;1;2;4",
}


def heldout_mask(tasks) -> np.ndarray:
    """Held-out episodes for the matrix: within each task, positions 1, 4, 7, ... (a third, every task)."""
    tasks = np.asarray(tasks)
    out = np.zeros(len(tasks), dtype=bool)
    for k in sorted(set(tasks.tolist())):
        idx = np.flatnonzero(tasks == k)
        out[idx[1::3]] = True
    return out


def subset(d: dict, mask: np.ndarray) -> dict:
    """The episodes of a ground-truth dict selected by a boolean mask."""
    return {k: (v[mask] if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == len(mask) else v)
            for k, v in d.items()}


def chamfer_mm(a, b):
    """Mean symmetric nearest-point distance (mm) of point sets a, b [E, T, M, 3], over episodes and frames."""
    import torch

    d = torch.cdist(a.flatten(0, 1), b.flatten(0, 1))
    return 1000.0 * float((0.5 * (d.min(-1).values.mean(-1) + d.min(-2).values.mean(-1))).mean())


def _twin(none: dict, companion_cfg: dict, table_height: float):
    """The companion and its batch for the episodes of ``none``, started at their ground truth's frame 0
    (table plane z = table_height, gravity -z)."""
    import torch

    from .companion import Companion, CompanionConfig

    comp = Companion(CompanionConfig(**companion_cfg))
    batch = comp.prepare([torch.as_tensor(g[0]) for g in none["gt"]], torch.tensor([0.0, 0.0, 1.0]),
                         -float(table_height), torch.tensor([0.0, 0.0, -9.81]), float(none["dt"]))
    return comp, batch


def _per_episode(term: str, value: list[float], episodes: int):
    """One value of a term repeated for every episode: [E] or [E, 3]."""
    import torch

    from .companion import effect_shape

    want = effect_shape(term)
    if len(value) != (want[0] if want else 1):
        raise ValueError(f"term {term} takes {want[0] if want else 1} number(s) per value, got {value}")
    th = torch.tensor(value, dtype=torch.float32)
    return th.expand(episodes, *want).clone() if want else th.reshape(()).expand(episodes).clone()


def perfect_nominal_gap(none: dict, eff: dict, term: str, value: list[float], companion_cfg: dict,
                        table_height: float) -> dict:
    """The most a twin channel could do for the gap: a nominal model that is exactly the effect-free
    ground truth, plus the twin's differential at ``value``; Chamfer and vertex RMS (mm) to the effect
    ground truth without and with it."""
    import torch

    comp, batch = _twin(none, companion_cfg, table_height)
    g0, g1 = torch.tensor(none["gt"]), torch.tensor(eff["gt"])
    cp, grip = torch.tensor(eff["cp"]), torch.tensor(eff["grip"])
    th = _per_episode(term, value, g0.shape[0])
    with torch.no_grad():
        x0 = comp.skin(batch, comp.rollout(batch, cp, grip))
        x1 = comp.skin(batch, comp.rollout(batch, cp, grip, {term: th}))
    pred = g0 + (x1 - x0)
    rms = lambda a: 1000.0 * float((a - g1).square().sum(-1).mean().sqrt())  # noqa: E731
    return {"chamfer_before_mm": round(chamfer_mm(g0, g1), 1), "chamfer_after_mm": round(chamfer_mm(pred, g1), 1),
            "rms_before_mm": round(rms(g0), 1), "rms_after_mm": round(rms(pred), 1)}


def nominal_error_mm(none: dict, companion_cfg: dict, table_height: float) -> float:
    """Mean distance (mm) of the companion's nominal rollout to the effect-free ground truth."""
    import torch

    comp, batch = _twin(none, companion_cfg, table_height)
    gt0 = torch.tensor(none["gt"])
    with torch.no_grad():
        x0 = comp.skin(batch, comp.rollout(batch, torch.tensor(none["cp"]), torch.tensor(none["grip"])))
    return 1000.0 * float((x0 - gt0).norm(dim=-1).mean())


def calibrate(none: dict, base: dict, trials: int, seed: int, table_height: float, log=print) -> dict:
    """Random search (``trials`` configs of :data:`SEARCH_SPACE`, ``base`` kept for the rest) for the
    companion closest to the effect-free ground truth; returns the best config (``base`` if none beats it)."""
    import random

    rng = random.Random(seed)
    best_cfg, best = dict(base), nominal_error_mm(none, base, table_height)
    log(f"calibrate: start {best:.1f} mm")
    for i in range(trials):
        cfg = dict(base)
        for k, space in SEARCH_SPACE.items():
            cfg[k] = rng.choice(space) if isinstance(space, list) else 10.0 ** rng.uniform(*space)
        err = nominal_error_mm(none, cfg, table_height)
        if err < best:
            best, best_cfg = err, cfg
            log(f"calibrate: trial {i}: {err:.1f} mm {json.dumps(cfg)}")
    log(f"calibrate: best {best:.1f} mm after {trials} trials")
    return best_cfg


def explained_table(none: dict, eff: dict, term: str, values: list[list[float]], companion_cfg: dict,
                    table_height: float, log=print) -> dict:
    """Nominal error, |D| and the explained fraction per value (module docstring)."""
    import torch

    if list(none["names"]) != list(eff["names"]) or none["gt"].shape != eff["gt"].shape:
        raise ValueError("the effect-free and effect datasets must hold the same episodes (same seed and count)")
    comp, batch = _twin(none, companion_cfg, table_height)
    gt0 = torch.tensor(none["gt"])
    D = torch.tensor(eff["gt"]) - gt0  # [E, T, M, 3]
    E = D.shape[0]
    tasks = np.asarray(eff["tasks"])
    groups = {"all": torch.ones(E, dtype=torch.bool)}
    groups.update({k: torch.tensor(tasks == k) for k in sorted(set(tasks.tolist()))})
    cp, grip = torch.tensor(eff["cp"]), torch.tensor(eff["grip"])
    res = {"episodes": E, "frames": int(D.shape[1]), "vertices": int(D.shape[2]), "rows": []}
    with torch.no_grad():
        t0 = time.time()
        x0 = comp.skin(batch, comp.rollout(batch, cp, grip))
        res["rollout_s"] = round(time.time() - t0, 2)
        res["nominal_error_mm"] = round(1000 * float((x0 - gt0).norm(dim=-1).mean()), 1)
        res["effect_mm"] = {k: round(1000 * float(D[m].norm(dim=-1).mean()), 1) for k, m in groups.items()}
        log(f"companion nominal error vs effect-free ground truth: {res['nominal_error_mm']} mm (mean over "
            f"episodes, frames, vertices; {E} episodes in {res['rollout_s']} s); world effect |D|: "
            + ", ".join(f"{k} {v} mm" for k, v in res["effect_mm"].items()))
        log(f"{'value':>16} " + " ".join(f"{k:>8}" for k in groups) + f" {'|Dc| mm':>8}")
        err = []  # [V, E] squared error per episode
        for v in values:
            Dc = comp.skin(batch, comp.rollout(batch, cp, grip, {term: _per_episode(term, v, E)})) - x0
            err.append((D - Dc).square().sum(dim=(1, 2, 3)))
            row = {"value": v, "mean_dc_mm": round(1000 * float(Dc.norm(dim=-1).mean()), 1), "explained": {}}
            for k, m in groups.items():
                row["explained"][k] = round(1.0 - float((D[m] - Dc[m]).square().sum() / D[m].square().sum()), 3)
            res["rows"].append(row)
            log(f"{','.join(f'{x:g}' for x in v):>16} " + " ".join(f"{row['explained'][k]:>+8.3f}" for k in groups)
                + f" {row['mean_dc_mm']:>8}")
        # upper bound: every episode gets its own best value of the grid (a shared value is what a fit gives)
        tot = D.square().sum(dim=(1, 2, 3))
        emin = torch.minimum(torch.stack(err).min(dim=0).values, tot)  # the value 0 is always allowed
        res["per_episode_best"] = {k: round(1.0 - float(emin[m].sum() / tot[m].sum()), 3) for k, m in groups.items()}
        log(f"{'per-episode best':>16} " + " ".join(f"{res['per_episode_best'][k]:>+8.3f}" for k in groups)
            + "    (upper bound: each episode its own value of the grid, or 0)")
    best = max(res["rows"], key=lambda r: r["explained"]["all"])
    res["best"] = {"value": best["value"], "explained": best["explained"]["all"]}
    log(f"best: {term}={best['value']} explains {best['explained']['all']:+.3f} of the world's effect displacement")
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.discrepancy_companion", description=__doc__.splitlines()[0])
    p.add_argument("--object", default="cloth", choices=["rope", "cloth"])
    p.add_argument("--effect", required=True, help="the world's effect (wind, air_drag, table_friction, slip, stiff, "
                                                   "heavy), or a comma-separated list of them with --term all")
    p.add_argument("--term", required=True, help="the companion's term (wind, linear_drag, quadratic_drag, "
                                                 "table_friction, gripper_slip, mass_scale), or 'all': every term "
                                                 "over its generic grid (GRIDS), a matrix effect x term")
    p.add_argument("--values", default=None, metavar="LIST", help="';'-separated values, ',' inside a vector "
                                                                  "(required unless --term all)")
    p.add_argument("--form", default="field", choices=["field", "pressure"], help="the companion's wind form")
    p.add_argument("--companion", default="{}", metavar="JSON", help="CompanionConfig overrides")
    p.add_argument("--calibrate", type=int, default=0, metavar="N",
                   help="first fit the companion's nominal config to the effect-free episodes: a random search "
                        "of N configs (seed --seed), the one with the lowest nominal error is used")
    p.add_argument("--in-sample", action="store_true", help="with --term all: choose and score each term's value "
                                                               "on all episodes (no hold-out)")
    p.add_argument("--episodes", type=int, default=12, metavar="N")
    p.add_argument("--seed", type=int, default=0, metavar="S")
    p.add_argument("--effects-config", default="effects_discrepancy", metavar="NAME|YAML")
    p.add_argument("--data-dir", required=True, metavar="DIR", help="datasets are generated here (or reused)")
    p.add_argument("--json", default=None, metavar="FILE", help="also write the results as JSON")
    args = p.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MUJOCO_GL", "egl")
    import torch

    from soma_ros.world import EFFECTS

    from .bench_core import machine_description
    from .companion import EFFECT_TERMS
    from .discrepancy import _generate, load_world

    effects = [e.strip() for e in args.effect.split(",") if e.strip()]
    bad = [e for e in effects if e not in EFFECTS]
    if bad or not effects:
        print(f"benchmarks.discrepancy_companion: error: unknown effect(s) {bad} (known: {', '.join(EFFECTS)})",
              file=sys.stderr)
        return 2
    every = args.term == "all"
    if not every and args.term not in EFFECT_TERMS:
        print(f"benchmarks.discrepancy_companion: error: unknown term {args.term!r} (known: {', '.join(EFFECT_TERMS)}, "
              f"all)", file=sys.stderr)
        return 2
    if not every and (len(effects) != 1 or args.values is None):
        print("benchmarks.discrepancy_companion: error: one --effect and --values are needed unless --term all",
              file=sys.stderr)
        return 2
    try:
        ccfg = dict(json.loads(args.companion), wind_form=args.form)
    except (json.JSONDecodeError, TypeError) as exc:
        print(f"benchmarks.discrepancy_companion: error: --companion is not a JSON object ({exc})", file=sys.stderr)
        return 2
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))
    print(machine_description("cpu"), flush=True)
    t0 = time.time()
    data = Path(args.data_dir)
    sets = {}
    for eff in ["none"] + effects:
        ds = _generate(args.object, data / f"{args.object}_{eff}", args.episodes, args.seed, eff, None, print,
                       args.effects_config)
        sets[eff] = ground_truth(ds)
    table_h = load_world(None, args.effects_config).table.height
    try:
        res = _study(args, effects, every, sets, ccfg, table_h)
    except ValueError as exc:
        print(f"benchmarks.discrepancy_companion: error: {exc}", file=sys.stderr)
        return 2
    res["seconds"] = round(time.time() - t0, 1)
    print(f"total {res['seconds']} s", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


def _study(args, effects: list[str], every: bool, sets: dict, ccfg: dict, table_h: float) -> dict:
    """The calibration and the table (one term) or the matrix (``--term all``) of :func:`main`."""
    if args.calibrate > 0:
        ccfg = calibrate(sets["none"], ccfg, args.calibrate, args.seed, table_h)
    if not every:
        res = explained_table(sets["none"], sets[effects[0]], args.term, _values(args.values), ccfg, table_h)
        res.update({"object": args.object, "effect": effects[0], "term": args.term, "companion": ccfg})
    else:
        res = {"object": args.object, "companion": ccfg, "grids": GRIDS, "matrix": {}, "winners": {}}
        quiet = lambda s: None  # noqa: E731
        held = heldout_mask(sets["none"]["tasks"])
        fit = ~held
        if args.in_sample:  # choose and score on the same (all) episodes
            held = fit = np.ones_like(held)
            print(f"every term over its grid; the value with the most explained on all {int(held.sum())} episodes, "
                  f"scored on the same episodes (in sample); companion {json.dumps(ccfg)}")
        else:
            print(f"every term over its grid; the value with the most explained on the {int(fit.sum())} fit episodes, "
                  f"scored on the {int(held.sum())} held-out ones (a third of each task); companion {json.dumps(ccfg)}")
        res["heldout"] = [str(n) for n in np.asarray(sets["none"]["names"])[held]]
        print(f"{'world effect':>16} " + " ".join(f"{t:>15}" for t in GRIDS)
              + "   winner, gap of the scored episodes with a perfect nominal model")
        for eff in effects:
            fit_n, fit_e = subset(sets["none"], fit), subset(sets[eff], fit)
            ho_n, ho_e = subset(sets["none"], held), subset(sets[eff], held)
            row = {}
            for t, g in GRIDS.items():
                v = explained_table(fit_n, fit_e, t, _values(g), ccfg, table_h, log=quiet)["best"]["value"]
                row[t] = {"value": v, "explained": explained_table(ho_n, ho_e, t, [v], ccfg, table_h,
                                                                     log=quiet)["best"]["explained"]}
            win = max(row, key=lambda t: row[t]["explained"])
            gap = perfect_nominal_gap(ho_n, ho_e, win, row[win]["value"], ccfg, table_h)
            res["matrix"][eff] = row
            res["winners"][eff] = {"term": win, **row[win], **gap}
            print(f"{eff:>16} " + " ".join(f"{row[t]['explained']:>+15.3f}" for t in GRIDS)
                  + f"   {win} {','.join(f'{x:g}' for x in row[win]['value'])}: Chamfer {gap['chamfer_before_mm']} -> "
                  f"{gap['chamfer_after_mm']} mm, vertex RMS {gap['rms_before_mm']} -> {gap['rms_after_mm']} mm",
                  flush=True)
    return res


if __name__ == "__main__":
    sys.exit(main())
