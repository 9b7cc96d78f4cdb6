"""Headroom of the discrepancy test: how far a perfect effect term could shrink the gap at all.

    python -m benchmarks.discrepancy_headroom --run RUN --none DATA/rope_none \
        --data DATA/rope_wind,DATA/rope_slip [--config default] [--json OUT.json]

Issue #8 asks that the held-out gap (depth RMSE and Chamfer of the unchanged model on measured data
with a hidden effect) at least halves once the named effect is added. Adding a term removes at
most the effect; what stays is about the model's own error on the same episodes without the effect,
the *floor*: the same metric of the unchanged model on the effect-free twin dataset (same world
seed and actions, so the same episodes). So

    headroom = before / floor        (a perfect effect term gives after / before ~ 1 / headroom)

and a dataset can pass the acceptance only where the headroom is about 2 or more on both metrics.
It is an estimate, not a strict bound: a term can also remove part of the model's own error
(docs/discrepancy.md, own-error control). The workflow's own conventions are used: its held-out
episodes (stratified by task), its passive-object rule and its evaluation frame stride, so the
figures are the ``gap_before`` that ``soma discrepancy`` and ``benchmarks.discrepancy`` report.
It also scores a *frozen object* on the effect-free twin (the first frame's splats, never moved:
:class:`trainer.baselines.StaticModel`) and prints frozen / floor, the metric's span over the
model. For depth RMSE on a thin or flat object it is close to a ceiling on any headroom: where the
simulated object misses the measured one, a pixel's error is the measured object's height above
whatever the simulation shows there, however far the miss, just as for a frozen object. So an
effect that leaves the object in the same height range can raise the model's depth RMSE to about
the frozen object's and no further; where frozen / floor is under 2, no such effect can be halved
on depth RMSE. (Chamfer has no such ceiling: an object blown off the table costs metres.)
It also scores the *ground truth's motion* (:func:`ground_truth_motion`, evaluation only): the
splats moved with the world's own vertices, the floor that the reconstruction and the renderer
set whatever the dynamics; a model cannot go below it, so before / oracle bounds what any term
could give. For information it also prints the same ratios for the depth RMSE over the union of the measured
and the simulated object's pixels (``rmse_union``, JSON ``union``), which also charges a simulated
object where the camera sees the table; it is not the acceptance's metric.

It needs one evaluation of the unchanged model per dataset, and one of the frozen object (rope,
6 held-out episodes: ~15 s each on one CPU core; cloth, 3: ~2 min), not the workflow's hour, and tells beforehand whether a test
of an effect at a given magnitude can pass with a given model.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional, Sequence

METRICS = ("rmse", "chamfer")
PASS = 2.0  # the acceptance halves the gap
#: for information, not the acceptance's: depth RMSE over the union of the measured and the simulated
#: object's pixels (symmetric: a simulated object where the camera sees the table costs too)
UNION = "rmse_union"


def headroom(before: dict, floor: dict, metrics: Sequence[str] = METRICS) -> dict:
    """{metric: before / floor} (None where the floor is missing or not positive); 'passable' when
    every metric's headroom is at least :data:`PASS`."""
    out: dict = {}
    for m in metrics:
        b, f = before.get(m), floor.get(m)
        out[m] = None if b is None or f is None or not f > 0 else float(b) / float(f)
    out["passable"] = all(out[m] is not None and out[m] >= PASS for m in metrics)
    return out


def ground_truth_motion(bags: dict):
    """EVALUATION ONLY (it reads the world's ground-truth topic, which no model or workflow may): a
    rollout model that moves every splat with its 3 nearest ground-truth vertices (inverse-square
    distance weights, translation only, fixed at frame 0); ``bags``: {episode name: its bag}. Its
    scores are what a model whose 3D motion were exact would get with this scene's splats: the floor
    the reconstruction and the renderer set, under any dynamics."""
    import torch

    from trainer.baselines import RolloutModel
    from trainer.evaluate_gt import read_ground_truth_points

    class GroundTruthMotion(RolloutModel):
        kind = "ground_truth_motion"

        def rollout(self, ep, init, scene):
            gt = torch.from_numpy(read_ground_truth_points(bags[ep.name],
                                                           stamps_ns=[int(t) for t in ep.stamps_ns.tolist()])).float()
            m0, c0 = init.means.detach().float(), init.covariances().detach().float()
            d, j = torch.cdist(m0, gt[0]).topk(min(3, gt.shape[1]), largest=False)
            w = 1.0 / (d + 1e-3).square()
            w = w / w.sum(dim=1, keepdim=True)
            for t in range(ep.num_frames):
                yield m0 + (w[..., None] * (gt[t][j] - gt[0][j])).sum(1), c0

    return GroundTruthMotion()


def heldout_context(run: Path, data: Path, cfg):
    """(EvalContext of ``data`` with the workflow's held-out episodes marked, the run's model as the
    workflow loads it): what ``soma discrepancy`` scores before / after on."""
    from trainer.config import load_train_config
    from trainer.discrepancy import load_model, mark_heldout
    from trainer.evaluate import EvalContext

    ctx = EvalContext(data, load_train_config(run / "train_config.yaml"), run / "scene")
    mark_heldout(ctx, cfg)
    return ctx, load_model(run / "checkpoint.pt", cfg)


def evaluate_heldout(models: dict, ctx, cfg, folders: Optional[dict] = None) -> dict:
    """{name: evaluate_models' result} of rollout ``models`` on the held-out episodes of ``ctx``, with the
    workflow's evaluation protocol (frame stride, no LPIPS); reports in ``folders`` where given."""
    from trainer.discrepancy import HELDOUT
    from trainer.evaluate import EvalConfig, evaluate_models
    from trainer.evaluate_metrics import EvalMetricsConfig

    ecfg = EvalConfig(metrics=EvalMetricsConfig(with_lpips=False), frame_stride=cfg.eval_frame_stride,
                      contact_sheets=False, progress=False)
    with tempfile.TemporaryDirectory() as tmp:
        where = {k: (folders or {}).get(k) or Path(tmp) / k for k in models}
        return evaluate_models(models, ctx, HELDOUT, where, ecfg, log=lambda *a: None)


def evaluate_unchanged(run: Path, data: Path, cfg, out: Optional[Path], frozen: bool = False) -> dict:
    """The unchanged model's metrics on the workflow's held-out episodes of ``data`` (metrics.json form);
    with ``frozen`` also, under key "frozen", those of a frozen object (:class:`trainer.baselines.StaticModel`:
    the first frame's splats, never moved) and under key "oracle" those of the ground truth's motion
    (:func:`ground_truth_motion`), scored in the same pass on the same episodes, frames and protocol."""
    from trainer.baselines import SimulatorModel, StaticModel
    from trainer.discrepancy import HELDOUT

    ctx, model = heldout_context(run, data, cfg)
    models = {"before": SimulatorModel(model)}
    if frozen:
        models["frozen"] = StaticModel()
        models["oracle"] = ground_truth_motion({r.name: r.bag for r in ctx.refs})
    every = evaluate_heldout(models, ctx, cfg, {"before": out})
    res = every["before"]
    if frozen:
        res["frozen"], res["oracle"] = every["frozen"], every["oracle"]
    res["tasks"] = {r.name: r.task for r in ctx.refs if r.split == HELDOUT}
    return res


def twin_mismatch(none: Path, data: Path) -> Optional[str]:
    """Why ``data`` is not the effect-free twin's counterpart (same object, preset, world seed and
    episodes: names, tasks, frame counts), or None."""
    a, b = (json.loads((d / "manifest.json").read_text()) for d in (none, data))
    for key in ("object", "preset", "seed"):
        if a.get(key) != b.get(key):
            return f"{key} {b.get(key)!r} vs {a.get(key)!r}"
    eps = [[(e["name"], e.get("task"), e.get("frames")) for e in m["episodes"]] for m in (a, b)]
    if eps[0] != eps[1]:
        return "different episodes (name, task, frames)"
    return None


def _fmt(x: Optional[float], digits: int = 4) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.discrepancy_headroom", description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, metavar="RUN", help="soma train run folder (the unchanged model)")
    p.add_argument("--none", required=True, metavar="DATA", help="effect-free twin dataset (same world seed)")
    p.add_argument("--data", required=True, metavar="LIST", help="comma-separated measured datasets, one effect each")
    p.add_argument("--config", default="default", metavar="NAME|YAML", help="workflow config (config/discrepancy)")
    p.add_argument("--out", default=None, metavar="DIR", help="also keep each evaluation's report here")
    p.add_argument("--json", default=None, metavar="FILE", help="write the table as JSON")
    args = p.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))
    from trainer.discrepancy import load_discrepancy_config

    run = Path(args.run)
    datasets = [Path(d) for d in args.data.split(",") if d]
    for d in [Path(args.none), *datasets]:
        if not (d / "manifest.json").is_file():
            print(f"discrepancy_headroom: error: {d}: no manifest.json (not a dataset folder)", file=sys.stderr)
            return 2
    if not (run / "checkpoint.pt").is_file():
        print(f"discrepancy_headroom: error: {run}: no checkpoint.pt (not a soma train run folder)", file=sys.stderr)
        return 2
    for d in datasets:
        why = twin_mismatch(Path(args.none), d)
        if why:
            print(f"discrepancy_headroom: error: {d} is not a twin of {args.none}: {why}", file=sys.stderr)
            return 2
    cfg = load_discrepancy_config(args.config)
    sub = (lambda d: Path(args.out) / d.name) if args.out else (lambda d: None)
    t0 = time.time()
    floor = evaluate_unchanged(run, Path(args.none), cfg, sub(Path(args.none)), frozen=True)
    frozen = floor.pop("frozen")
    oracle = floor.pop("oracle")
    print(f"run {run}; floor = unchanged model on {args.none} ({len(floor['tasks'])} held-out episodes, "
          f"{time.time() - t0:.0f} s): depth RMSE {_fmt(floor['mean']['rmse'])} m, "
          f"Chamfer {_fmt(floor['mean']['chamfer'])} m", flush=True)
    span = headroom(frozen["mean"], floor["mean"])
    span_u = headroom(frozen["mean"], floor["mean"], (UNION,))[UNION]
    print(f"frozen object on {args.none} (the first frame never moved): depth RMSE {_fmt(frozen['mean']['rmse'])} m "
          f"({_fmt(span['rmse'], 2)}x the floor), Chamfer {_fmt(frozen['mean']['chamfer'])} m "
          f"({_fmt(span['chamfer'], 2)}x); union depth RMSE {_fmt(floor['mean'].get(UNION))} m (floor), "
          f"{_fmt(frozen['mean'].get(UNION))} m ({_fmt(span_u, 2)}x)", flush=True)
    below = headroom(oracle["mean"], floor["mean"])
    print(f"ground-truth motion on {args.none} (splats moved with the world's vertices: exact dynamics): depth RMSE "
          f"{_fmt(oracle['mean']['rmse'])} m ({_fmt(below['rmse'], 2)}x the floor), Chamfer "
          f"{_fmt(oracle['mean']['chamfer'])} m ({_fmt(below['chamfer'], 2)}x)", flush=True)
    rows = {}
    for d in datasets:
        t1 = time.time()
        before = evaluate_unchanged(run, d, cfg, sub(d))
        h = headroom(before["mean"], floor["mean"])
        per = {ep: {**headroom(v, floor["episodes"][ep]), "task": before["tasks"][ep],
                    **{f"{m}_before": v.get(m) for m in METRICS}} for ep, v in before["episodes"].items()}
        hu = headroom(before["mean"], floor["mean"], (UNION,))[UNION]
        rows[d.name] = {"before": {m: before["mean"].get(m) for m in METRICS}, "headroom": h, "episodes": per,
                        "union": {"before": before["mean"].get(UNION), "headroom": hu}}
        print(f"{d.name}: depth RMSE {_fmt(before['mean']['rmse'])} m (headroom {_fmt(h['rmse'], 2)}x), "
              f"Chamfer {_fmt(before['mean']['chamfer'])} m (headroom {_fmt(h['chamfer'], 2)}x) -> "
              f"{'can' if h['passable'] else 'cannot'} halve both ({time.time() - t1:.0f} s); "
              f"union depth RMSE {_fmt(before['mean'].get(UNION))} m ({_fmt(hu, 2)}x)", flush=True)
        for ep, e in per.items():
            print(f"    {ep} ({e['task']}): RMSE {_fmt(e['rmse_before'])} ({_fmt(e['rmse'], 2)}x)  "
                  f"Chamfer {_fmt(e['chamfer_before'])} ({_fmt(e['chamfer'], 2)}x)")
    if args.json:
        Path(args.json).write_text(json.dumps({"run": str(run), "none": str(args.none), "floor": floor["mean"],
                                               "frozen": {"metrics": frozen["mean"], "vs_floor": span},
                                               "oracle": {"metrics": oracle["mean"], "vs_floor": below},
                                               "datasets": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
