"""Identifiability check of the discrepancy ranking when the model is exact apart from the hidden term.

    python -m benchmarks.discrepancy_synthetic --run RUN --data CLEAN --out DIR [--cases wind,table_friction,...]

The "world" is the trained model itself with one hidden effect term of a set magnitude added
(``none``: no term, the negative control); the observed points of every scored frame are that
model's splat centres (an evenly strided subset, like the workflow's subsample of the fused
depth). The ranking of :func:`trainer.discrepancy.rank_candidates` then runs unchanged on the
run's episodes (actions and initial states of CLEAN). This isolates the statistics and the
candidate fits from the learned model's own error, which dominates on reference-world data with
a CI-sized model (see the benchmark report); it does not replace :mod:`benchmarks.discrepancy`.

Hidden magnitudes (physical, fixed before running, not tuned): wind 1 m/s^2 along +y; table_friction
mu = -0.5 (a table more slippery than learned); gripper_slip sag = 0.5 g; mass_scale excess = 2
(3x the mass); linear_drag 2 /s.

``--hidden-pathway``: how the hidden term acts in the world. ``direct`` (default): as a direct
effect (explicitly integrated force on top of the model, like a physical force the model lacks);
``feature``: only as a network input feature (what this benchmark did before direct effects
existed). The candidates' pathway is the workflow config's ``direct``.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import time
from pathlib import Path

HIDDEN = {
    "none": None,
    "wind": {"name": "wind", "params": {"accel": [0.0, 1.0, 0.0]}},
    "table_friction": {"name": "table_friction", "params": {"mu": -0.5}},
    "gripper_slip": {"name": "gripper_slip", "params": {"sag": 0.5}},
    "mass_scale": {"name": "mass_scale", "params": {"excess": 2.0}},
    "linear_drag": {"name": "linear_drag", "params": {"coeff": 2.0}},
}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.discrepancy_synthetic", description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, metavar="RUN")
    p.add_argument("--data", required=True, metavar="CLEAN", help="dataset giving actions and initial states")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--cases", default="none,wind,table_friction,gripper_slip,mass_scale")
    p.add_argument("--config", default="default", metavar="NAME|YAML")
    p.add_argument("--fit-iters", type=int, default=None)
    p.add_argument("--frame-stride", type=int, default=None)
    p.add_argument("--hidden-pathway", choices=("direct", "feature"), default="direct")
    p.add_argument("--candidates", default=None, help="comma list overriding the config's candidates")
    p.add_argument("--max-fit-episodes", type=int, default=None)
    p.add_argument("--max-heldout-episodes", type=int, default=None)
    args = p.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from trainer.config import load_train_config
    from trainer.discrepancy import (EpisodeObs, _rollout, heldout_names, load_discrepancy_config, load_model,
                                     rank_candidates, residual_per_frame)
    from trainer.evaluate import EvalContext

    over = {}
    if args.fit_iters is not None:
        over["fit_iters"] = args.fit_iters
    if args.frame_stride is not None:
        over["frame_stride"] = args.frame_stride
    if args.candidates:
        over["candidates"] = [c.strip() for c in args.candidates.split(",") if c.strip()]
    if args.max_fit_episodes is not None:
        over["max_fit_episodes"] = args.max_fit_episodes
    if args.max_heldout_episodes is not None:
        over["max_heldout_episodes"] = args.max_heldout_episodes
    cfg = load_discrepancy_config(args.config, over)
    run = Path(args.run)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ctx = EvalContext(args.data, load_train_config(run / "train_config.yaml"), run / "scene", cache_dir=out / "cache")
    sim = load_model(run / "checkpoint.pt", cfg)
    refs = ctx.refs
    hold = set(heldout_names(refs, cfg))
    held = [r for r in refs if r.name in hold]
    fit = [r for r in refs if r.name not in hold]
    if cfg.max_fit_episodes:
        fit = fit[: cfg.max_fit_episodes]
    if cfg.max_heldout_episodes:
        held = held[: cfg.max_heldout_episodes]
    proto = {}
    for r in fit + held:
        ep = ctx.store.episode(r.name)
        proto[r.name] = (r, ep.dt, ep.control_points.float().clone(), ep.gripper.float().clone(),
                         ctx.store.initial_splats(r.name), list(range(cfg.frame_stride, ep.num_frames, cfg.frame_stride)))
    rows = []
    for case in [c.strip() for c in args.cases.split(",") if c.strip()]:
        if case not in HIDDEN:
            print(f"error: unknown case {case!r} (known: {', '.join(HIDDEN)})", file=sys.stderr)
            return 2
        t0 = time.time()
        true = copy.deepcopy(sim)
        if HIDDEN[case] is not None:
            true.add_effect({**HIDDEN[case], "direct": args.hidden_pathway == "direct"})
        true.eval()
        obs = {}
        truth = {}
        for name, (r, dt, cp, gr, init, frames) in proto.items():
            ob = EpisodeObs(name, r.task, r.split, float(dt), cp, gr, init, frames, [])
            with torch.no_grad():
                states = [st.means.detach().float().clone() for _, st in _rollout(true, ob, ctx.scene, frames)]
            n = states[0].shape[0]
            pick = torch.linspace(0, n - 1, min(cfg.max_points, n)).round().long()
            ob.points = [s[pick] for s in states]
            obs[name] = ob
            truth[name] = states
        fit_obs = [obs[r.name] for r in fit]
        held_obs = [obs[r.name] for r in held]
        base = [residual_per_frame(sim, o, ctx.scene) for o in held_obs]
        print(f"[{case}] held-out residual without any term: {1000 * float(np.mean(np.concatenate(base))):.2f} mm", flush=True)
        named, ranking, decision, fits, models, _ = rank_candidates(sim, fit_obs, held_obs, base, ctx.scene, cfg,
                                                                    log=lambda s: print(s, flush=True))
        after = models[named] if named != "none" else sim
        res_after = [residual_per_frame(after, o, ctx.scene) for o in held_obs]
        want = "none" if HIDDEN[case] is None else HIDDEN[case]["name"]
        row = {"hidden": case, "hidden_spec": HIDDEN[case], "named": named, "match": named == want,
               "ranking": ranking, "decision": decision,
               "fitted": fits[named]["parameters"] if named != "none" else {},
               "points_before": float(np.mean(np.concatenate(base))),
               "points_after": float(np.mean(np.concatenate(res_after))), "seconds": round(time.time() - t0, 1)}
        rows.append(row)
        print(f"[{case}] named {named} match {row['match']} points {row['points_before']:.5f} -> {row['points_after']:.5f}",
              flush=True)
        (out / "synthetic.json").write_text(json.dumps(rows, indent=1, default=float))
    lines = ["# Discrepancy ranking, synthetic (model = world + hidden term)", "",
             f"run `{run}`, data `{args.data}`, config `{args.config}` {over}, candidates direct: {cfg.direct}, "
             f"hidden pathway: {args.hidden_pathway}", "",
             "| hidden | named | match | top explained (±std) | runner-up | 3D residual before → after (mm) | fitted |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        t = r["ranking"][0]
        s = r["ranking"][1] if len(r["ranking"]) > 1 else None
        lines.append(f"| {r['hidden']} | {r['named']} | {'yes' if r['match'] else 'NO'} | {t['name']} "
                     f"{t['explained_fraction']:+.3f}±{t['uncertainty']:.3f} | "
                     f"{'' if s is None else s['name'] + ' ' + format(s['explained_fraction'], '+.3f')} | "
                     f"{1000 * r['points_before']:.2f} → {1000 * r['points_after']:.2f} | "
                     f"{json.dumps({k: [round(x, 3) for x in v] for k, v in r['fitted'].items()})} |")
    (out / "table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
