"""Score a trained model with given effect terms added, on the discrepancy workflow's held-out episodes.

    python -m benchmarks.discrepancy_terms --run RUN --data MEASURED --config physics \
        --variants '{"loosen 3": [{"name": "gripper_slip", "loosen": 3.0}]}'

Each variant (a name -> a list of effect specs, as ``Simulator.add_effect`` takes them; ``direct``
defaults to the workflow config's) is the unchanged model of ``RUN`` with those terms added by hand,
rolled out open loop on the held-out episodes the workflow would score (same split, frames and
protocol as ``soma discrepancy``'s before / after), and its depth RMSE and Chamfer are printed with the
unchanged model's. It answers "what would the gap be if the workflow had found this term at this
value": the best a candidate can do at all, independent of the fit.

``--objective`` also prints each variant's value of the workflow's fit objective: the 3D residual
(depth back-projected against the simulated splats, ``trainer.discrepancy.residual_per_frame``) summed
over the scored frames of the fit episodes, and of the held-out ones. It tells a fit that stopped
short (a variant the objective prefers to the fitted values) from an objective that prefers the
wrong term.

``--breakdown`` also prints where each variant's depth error lives (scored pixels by rendered
opacity: covered, edge, missed; ``trainer.evaluate_metrics.depth_error_shares``);
``--heights K`` prints how far each variant lifts the object (its highest splat's rise above frame 0,
every K-th frame of every held-out episode); ``--ends F1,F2`` where each arm's end hangs at those
frames, in the world and in every model (a held rope's droop; evaluation only); ``--direct-splats``
runs every model with ``dynamics.direct_splats`` on. ``--ground-truth-motion`` adds a row for the splats moved by the world's ground-truth motion
(EVALUATION ONLY: it reads the ground-truth topic; ``benchmarks.discrepancy_headroom``), the floor
the reconstruction and the renderer set.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import sys
import time
from pathlib import Path
from typing import Optional

UNCHANGED = "unchanged"
GROUND_TRUTH_MOTION = "ground-truth motion"


def parse_variants(text: str) -> dict[str, list[dict]]:
    """``'{"name": [spec, ...], ...}'`` -> the dict, checked: every spec a dict with a ``name``."""
    try:
        variants = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"--variants is not JSON: {e}") from None
    if not isinstance(variants, dict) or not variants:
        raise ValueError("--variants must be a non-empty JSON object {name: [effect spec, ...]}")
    for name, specs in variants.items():
        if name in (UNCHANGED, GROUND_TRUTH_MOTION):
            raise ValueError(f"variant name {name!r} is reserved ({UNCHANGED!r}: the model as trained, "
                             f"{GROUND_TRUTH_MOTION!r}: --ground-truth-motion)")
        if not isinstance(specs, list) or not all(isinstance(s, dict) and "name" in s for s in specs):
            raise ValueError(f"variant {name!r}: expected a list of effect specs with a 'name', got {specs!r}")
    return variants


def build_models(run: Path, data: Path, variants: dict[str, list[dict]], config: str = "default",
                 ground_truth_motion: bool = False, direct_splats: bool = False):
    """(the workflow's held-out context of ``data``, its config, {name: rollout model}): the model as
    trained under ``"unchanged"``, one per variant, the ground truth's motion if asked.
    ``direct_splats``: every model with ``dynamics.direct_splats`` on (the direct terms also move the
    splats within their fine clusters; :class:`soma_ros.core.config.DynamicsConfig`)."""
    from benchmarks.discrepancy_headroom import ground_truth_motion as gt_motion, heldout_context
    from trainer.baselines import SimulatorModel
    from trainer.discrepancy import load_discrepancy_config

    cfg = load_discrepancy_config(config)
    ctx, base = heldout_context(run, data, cfg)
    if direct_splats:
        base.config.dynamics.direct_splats = True
    models = {UNCHANGED: SimulatorModel(base)}
    for name, specs in variants.items():
        sim = copy.deepcopy(base)
        for spec in specs:
            sim.add_effect({"direct": cfg.direct, **spec})
        models[name] = SimulatorModel(sim)
    if ground_truth_motion:
        models[GROUND_TRUTH_MOTION] = gt_motion({r.name: r.bag for r in ctx.refs})
    return ctx, cfg, models


class HeldoutRollouts:
    """Every model's splat centres ([N, 3] float per frame) on every held-out episode, each model rolled
    out once per episode on first use and kept, so the diagnostics (``--heights``, ``--arms``,
    ``--ends``) share one rollout instead of each rolling every model out again."""

    def __init__(self, ctx, models: dict) -> None:
        self.ctx, self.models = ctx, models
        self._kept: dict[tuple[str, str], list] = {}

    def means(self, name: str, episode: str) -> list:
        key = (name, episode)
        if key not in self._kept:
            import torch

            ep, init = self.ctx.store.episode(episode), self.ctx.store.initial_splats(episode)
            with torch.no_grad():
                self._kept[key] = [m.detach().float().clone()
                                   for m, _ in self.models[name].rollout(ep, init, self.ctx.scene)]
        return self._kept[key]


def rollout_heights(ctx, models: dict, rolls: Optional[HeldoutRollouts] = None) -> dict[str, dict[str, list[float]]]:
    """{model: {held-out episode: [m per frame]}}: how far the object's highest splat has risen above
    its height in the first frame (along the table's normal), every frame of the open-loop rollout."""
    import torch

    from trainer.discrepancy import HELDOUT

    rolls = rolls or HeldoutRollouts(ctx, models)
    n = torch.as_tensor(ctx.scene.plane_normal, dtype=torch.float32)
    out: dict[str, dict[str, list[float]]] = {name: {} for name in models}
    for ref in ctx.episodes(HELDOUT):
        for name in models:
            top = [float((means @ n).max()) for means in rolls.means(name, ref.name)]
            out[name][ref.name] = [h - top[0] for h in top]
    return out


def fit_objective(ctx, cfg, models: dict) -> dict[str, tuple[float, float, Optional[float], Optional[float]]]:
    """{model: (3D residual sum over the fit episodes' scored frames, the same over the held-out
    ones, |wrist load error| sum (N) over the fit episodes' scored frames, the same held out)}: the
    workflow's fit objective (``trainer.discrepancy.scores_per_frame``) and the load channel its
    ranking also scores (None where an episode has no ``/joint_states`` efforts), for every
    :class:`~trainer.baselines.SimulatorModel` in ``models`` (others, e.g. the ground truth's
    motion, are skipped)."""
    import torch

    from trainer.baselines import SimulatorModel
    from trainer.discrepancy import HELDOUT, episode_obs, scores_per_frame

    obs = [(ref.split == HELDOUT, episode_obs(ctx, ref, cfg)[0]) for ref in ctx.refs]
    if not any(h for h, _ in obs) or all(h for h, _ in obs):
        raise ValueError("the data needs both fit and held-out episodes for --objective")
    with_load = all(ob.load is not None for _, ob in obs)
    out: dict[str, tuple[float, float, Optional[float], Optional[float]]] = {}
    for name, model in models.items():
        if not isinstance(model, SimulatorModel):
            continue
        sums = [0.0, 0.0, 0.0, 0.0]
        with torch.no_grad():
            for held, ob in obs:
                res, load = scores_per_frame(model.sim, ob, ctx.scene)
                sums[int(held)] += float(res.sum())
                if with_load:
                    sums[2 + int(held)] += float(load.sum())
        out[name] = (sums[0], sums[1], sums[2] if with_load else None, sums[3] if with_load else None)
    return out


def sidecar_grasp(data: Path, episode: str) -> Optional[tuple[list[float], list[int], int]]:
    """(the world's grasp point [3], the vertices it held, the object's vertex count) from the episode's
    sidecar (``<episode>.meta.json``; EVALUATION ONLY: a diagnostic, never the workflow's input), or
    None where the sidecar or its grasp is missing."""
    try:
        m = json.loads((data / f"{episode}.meta.json").read_text())
        tcp = [float(v) for v in m["grasp"]["tcp"]]
        held = sorted(int(i) for i in m["grasp"]["held_vertices"])
        n = int(m["object_params"]["n_vertices"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return tcp, held, n


def world_grasp(data: Path, episode: str) -> str:
    """The suffix " (the world held vertices [...] of N)" from the episode's sidecar, or "" without one."""
    g = sidecar_grasp(data, episode)
    return "" if g is None else f" (the world held vertices {g[1]} of {g[2]})"


def _grasped_heldout(ctx, data: Path, frames: list[int], option: str):
    """(held-out episode ref, its sidecar grasp) for every held-out episode with a grasp in its sidecar;
    ValueError naming ``option`` where a frame is outside an episode."""
    from trainer.discrepancy import HELDOUT

    for ref in ctx.episodes(HELDOUT):
        g = sidecar_grasp(data, ref.name)
        if g is None:
            continue
        last = ctx.store.episode(ref.name).num_frames - 1
        bad = [f for f in frames if not 0 <= f <= last]
        if bad:
            raise ValueError(f"{option}: frames {bad} are outside {ref.name}'s 0..{last}")
        yield ref, g


ARM_BINS = (0.0, 0.05, 0.10, 0.15, 0.20, float("inf"))  # m from the grasp point, horizontally


def arm_errors(ctx, models: dict, data: Path, frames: list[int], rolls: Optional[HeldoutRollouts] = None) -> dict:
    """EVALUATION ONLY (the ground truth's motion and the world's sidecar): {held-out episode: {"held":
    [vertex], "count": [splats per bin], "errors": {frame: {model: [(mean |e|, mean e_z) m per bin, or
    None where a bin is empty]}}}}, e = a model's splat minus the same splat moved by the ground truth's
    motion, the bins :data:`ARM_BINS` of each splat's horizontal distance at frame 0 from the world's
    grasp point (along the table, its z the world's up). Episodes without a grasp in the sidecar are
    left out."""
    import torch

    rolls = rolls or HeldoutRollouts(ctx, models)
    out = {}
    for ref, g in _grasped_heldout(ctx, data, frames, "--arms"):
        tcp, held = torch.tensor(g[0], dtype=torch.float32), g[1]
        roll = {name: rolls.means(name, ref.name) for name in models}
        truth = roll[GROUND_TRUTH_MOTION]
        dist = (truth[0][:, :2] - tcp[:2]).norm(dim=1)  # [N]
        sel = [(dist >= a) & (dist < b) for a, b in zip(ARM_BINS[:-1], ARM_BINS[1:])]
        errors = {}
        for f in frames:
            errors[f] = {}
            for name, r in roll.items():
                if name == GROUND_TRUTH_MOTION:
                    continue
                e = r[f] - truth[f]  # [N, 3]
                errors[f][name] = [(float(e[s].norm(dim=1).mean()), float(e[s][:, 2].mean())) if bool(s.any()) else None
                                   for s in sel]
        out[ref.name] = {"held": held, "count": [int(s.sum()) for s in sel], "errors": errors}
    return out


def print_arm_errors(ctx, models: dict, data: Path, frames: list[int], rolls: Optional[HeldoutRollouts] = None) -> None:
    res = arm_errors(ctx, models, data, frames, rolls)
    edges = [f"{100 * a:.0f}-{100 * b:.0f}" if math.isfinite(b) else f"{100 * a:.0f}+"
             for a, b in zip(ARM_BINS[:-1], ARM_BINS[1:])]
    print("splats against the ground truth's motion, mean |error| and mean vertical error (mm), by distance (cm) "
          "from the world's grasp point: " + " | ".join(edges))
    for episode, r in res.items():
        print(f"  {episode} (the world held vertices {r['held']}; splats per bin {r['count']})")
        for f, per in r["errors"].items():
            for name, cells in per.items():
                print(f"    frame {f:3d} {name:>16s}: " + " | ".join(
                    "      -      " if c is None else f"{1000 * c[0]:5.1f} z{1000 * c[1]:+6.1f}" for c in cells))


END_SPLATS = 10  # splats nearest each end vertex of the world's rope at frame 0 stand for the model's end


def arm_ends(ctx, models: dict, data: Path, frames: list[int], rolls: Optional[HeldoutRollouts] = None) -> dict:
    """EVALUATION ONLY (the ground-truth topic and the world's sidecar): {held-out episode: {"held":
    [vertex], "ends": {frame: {"world" or model: [[along, up] of the first end, [along, up] of the last]}}}}
    in m, relative to the world's middle held vertex at that frame, "along" horizontal along the
    rope's first-to-last vertex direction at frame 0: where each arm of a held line object hangs, the
    world's and every model's (its :data:`END_SPLATS` splats nearest the world's end vertex at frame 0).
    Episodes without a grasp in the sidecar are left out."""
    import numpy as np

    from trainer.evaluate_gt import read_ground_truth_points

    rolls = rolls or HeldoutRollouts(ctx, models)
    out = {}
    for ref, g in _grasped_heldout(ctx, data, frames, "--ends"):
        held = g[1]
        world = read_ground_truth_points(data / ref.name)  # [T, M, 3]
        mid = world[:, held[len(held) // 2]]  # [T, 3]
        axis = world[0][-1, :2] - world[0][0, :2]
        axis = axis / max(float(np.linalg.norm(axis)), 1e-9)

        def rel(p, f):
            d = np.asarray(p, dtype=float) - mid[f]
            return [float(d[:2] @ axis), float(d[2])]

        ends = {f: {"world": [rel(world[f][0], f), rel(world[f][-1], f)]} for f in frames}
        for name in models:
            roll = rolls.means(name, ref.name)
            start = roll[0].double().numpy()
            picks = [np.argsort(np.linalg.norm(start - world[0][i], axis=1))[:END_SPLATS] for i in (0, -1)]
            for f in frames:
                at = roll[f].double().numpy()
                ends[f][name] = [rel(at[k].mean(0), f) for k in picks]
        out[ref.name] = {"held": held, "ends": ends}
    return out


def print_arm_ends(ctx, models: dict, data: Path, frames: list[int], rolls: Optional[HeldoutRollouts] = None) -> None:
    res = arm_ends(ctx, models, data, frames, rolls)
    print("arm ends (first vertex's, last vertex's) relative to the world's middle held vertex, cm: "
          "(along the rope, up)")
    for episode, r in res.items():
        print(f"  {episode} (the world held vertices {r['held']})")
        for f, per in r["ends"].items():
            print(f"    frame {f:3d}: " + " | ".join(
                f"{name} " + " ".join(f"({100 * a:+5.1f},{100 * u:+5.1f})" for a, u in e) for name, e in per.items()))


def _ratio(value, base, scale: float, unit: str) -> str:
    if value is None or base is None:
        return "n/a"
    rel = f" ({value / base:.2f}x)" if base > 0 else ""
    return f"{scale * value:.4g} {unit}{rel}"


def _frames(option: str, text: Optional[str]) -> list[int]:
    """``"40,79"`` -> [40, 79] (None -> []); ValueError naming ``option`` otherwise."""
    if text is None:
        return []
    try:
        return [int(f) for f in text.split(",")]
    except ValueError:
        raise ValueError(f"{option} takes frame numbers like 40,79, got {text!r}") from None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.discrepancy_terms", description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, metavar="RUN", help="soma train run folder")
    p.add_argument("--data", required=True, metavar="MEASURED", help="measured dataset")
    p.add_argument("--variants", required=True, metavar="JSON", help='{"name": [effect spec, ...], ...}')
    p.add_argument("--config", default="default", metavar="NAME|YAML", help="workflow config (config/discrepancy)")
    p.add_argument("--json", default=None, metavar="FILE", help="also write {variant: {metric: value}} here")
    p.add_argument("--breakdown", action="store_true", help="also print where the depth error lives (by rendered opacity)")
    p.add_argument("--heights", type=int, default=0, metavar="K",
                   help="also print every K-th frame's rise (cm) of the object's highest splat, per held-out episode")
    p.add_argument("--objective", action="store_true",
                   help="also print the workflow's fit objective (3D residual sum) on the fit and held-out episodes")
    p.add_argument("--per-episode", action="store_true",
                   help="also print every held-out episode's scores, with where the world held the object "
                        "(its sidecar, evaluation only)")
    p.add_argument("--arms", default=None, metavar="F1,F2,...",
                   help="with --ground-truth-motion: at these frames, every model's splats against the ground "
                        "truth's motion, by their distance from where the world held the object (sidecar)")
    p.add_argument("--ends", default=None, metavar="F1,F2,...",
                   help="also print, at these frames, where each arm's end hangs in the world and in every model "
                        "(ground-truth topic and sidecar: evaluation only)")
    p.add_argument("--direct-splats", action="store_true",
                   help="run every model with dynamics.direct_splats on (direct terms also move splats within "
                        "their fine clusters)")
    p.add_argument("--ground-truth-motion", action="store_true",
                   help="add the splats moved by the ground truth's motion (evaluation only: reads the ground-truth topic)")
    args = p.parse_args(argv)
    try:
        variants = parse_variants(args.variants)
    except ValueError as e:
        print(f"discrepancy_terms: error: {e}", file=sys.stderr)
        return 2
    try:
        arm_frames, end_frames = _frames("--arms", args.arms), _frames("--ends", args.ends)
        if arm_frames and not args.ground_truth_motion:
            raise ValueError("--arms needs --ground-truth-motion")
    except ValueError as e:
        print(f"discrepancy_terms: error: {e}", file=sys.stderr)
        return 2
    run = Path(args.run)
    if not (run / "checkpoint.pt").is_file():
        print(f"discrepancy_terms: error: {run} has no checkpoint.pt (a soma train run folder)", file=sys.stderr)
        return 2
    from soma_ros.core.config import ConfigError

    from benchmarks.discrepancy_headroom import evaluate_heldout

    t0 = time.time()
    try:
        ctx, cfg, models = build_models(run, Path(args.data), variants, args.config, args.ground_truth_motion,
                                        args.direct_splats)
        res = evaluate_heldout(models, ctx, cfg)
    except (ConfigError, FileNotFoundError) as e:  # an unknown effect or parameter, a missing dataset
        print(f"discrepancy_terms: error: {e}", file=sys.stderr)
        return 2
    print(f"run {run}, data {args.data}, {len(res[UNCHANGED]['episodes'])} held-out episodes ({time.time() - t0:.0f} s)")
    base = res[UNCHANGED]["mean"]
    for name, r in res.items():
        m = r["mean"]
        print(f"  {name:>16s}: depth RMSE {m['rmse']:.4f} m ({m['rmse'] / base['rmse']:.2f}x), "
              f"Chamfer {1000 * m['chamfer']:.1f} mm ({m['chamfer'] / base['chamfer']:.2f}x)", flush=True)
        if args.breakdown:
            from trainer.evaluate_metrics import depth_error_shares

            shares = depth_error_shares(m)
            print("                    " + "; ".join(
                f"{c} {100 * v['pixels']:.1f}% of pixels, {100 * v['error']:.1f}% of the squared error, rms {v['rms']:.4f} m"
                for c, v in shares.items()), flush=True)
    if args.per_episode:
        print("per held-out episode: depth RMSE m (x the unchanged model's on it), Chamfer mm (x):")
        for episode, b in res[UNCHANGED]["episodes"].items():
            print(f"  {episode}{world_grasp(Path(args.data), episode)}")
            for name, r in res.items():
                print(f"    {name:>20s}: " + ", ".join(
                    _ratio(r["episodes"][episode].get(k), b.get(k), scale, unit)
                    for k, scale, unit in (("rmse", 1.0, "m"), ("chamfer", 1000.0, "mm"))), flush=True)
    rolls = HeldoutRollouts(ctx, models)  # shared by the diagnostics below
    try:
        if arm_frames:
            print_arm_errors(ctx, models, Path(args.data), arm_frames, rolls)
        if end_frames:
            print_arm_ends(ctx, models, Path(args.data), end_frames, rolls)
    except ValueError as e:  # a frame outside an episode
        print(f"discrepancy_terms: error: {e}", file=sys.stderr)
        return 2
    if args.objective:
        try:
            objective = fit_objective(ctx, cfg, models)
        except ValueError as e:  # data without fit episodes
            print(f"discrepancy_terms: error: {e}", file=sys.stderr)
            return 2
        print("the workflow's fit objective (3D residual summed over the scored frames, m; lower is better)"
              " and the |wrist load error| summed over the same frames, N (where the episodes have efforts):")
        for name, (fit_sum, held_sum, fit_load, held_load) in objective.items():
            load = "" if fit_load is None else f"; wrist load fit {fit_load:.3f} N, held-out {held_load:.3f} N"
            print(f"  {name:>16s}: fit episodes {fit_sum:.4f}, held-out episodes {held_sum:.4f}{load}", flush=True)
    if args.heights > 0:
        heights = rollout_heights(ctx, models, rolls)
        print(f"rise of the highest splat above frame 0, cm, every {args.heights} frames:")
        for episode in next(iter(heights.values())):
            for name, per in heights.items():
                print(f"  {episode} {name:>20s}: " + " ".join(f"{100 * h:3.0f}" for h in per[episode][::args.heights]))
    if args.json:
        Path(args.json).write_text(json.dumps({k: {"rmse": r["mean"]["rmse"], "chamfer": r["mean"]["chamfer"]}
                                               for k, r in res.items()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
