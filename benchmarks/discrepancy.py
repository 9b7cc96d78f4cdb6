"""Discrepancy benchmark (issue #8): hide one effect in measured data and check the workflow names it.

    python -m benchmarks.discrepancy --object rope --effects wind,table_friction,slip --out DIR
    python -m benchmarks.discrepancy --object rope --effects wind --run RUN --out DIR   # reuse a trained run

1. A model trained on effect-free reference-world data (``--run`` reuses one; else OUT/data/<obj>_none
   is generated and ``soma train`` runs with ``--train-config``, default tiny).
2. For every hidden effect (and ``none``, the negative control, unless ``--no-negative``): measured data
   from the same world and seed with that effect switched on (OUT/data/<obj>_<effect>). And the
   workflow's own-error reference: ``--reference-episodes`` effect-free episodes of world seed + 1
   (OUT/data/<obj>_reference), which neither the model nor the measured data contain.
3. The workflow (:func:`soma_ros.discrepancy.workflow.run_discrepancy`) on it -> OUT/<effect>/report.{md,json}.
4. Scoring (the benchmark, not the workflow, reads the evaluation sidecars ``<episode>.meta.json``
   to learn which effect is on): OUT/table.md and OUT/bench.json with, per hidden effect, the named
   effect, whether it matches, the explained fractions and the held-out gap before/after (depth RMSE,
   Chamfer) with two shrink factors (acceptance: named correctly and halved on both metrics):

   * raw: after / before of the metric on the effect data;
   * effect-attributable (excess): (after - floor) / (before - floor), where the floor is the same
     metric of the unchanged model on the effect-free twin dataset (same world seed, same actions,
     same held-out episodes), i.e. the workflow's gap_before on ``none``. The raw gap can never halve
     while the model's own error (the floor) is most of it; the excess is the part the hidden effect
     adds. ``none`` is processed first so the floor exists (without it, e.g. ``--no-negative``, the
     excess columns are n/a).

Use ``--effects-config effects_discrepancy`` (config/world/effects_discrepancy.yaml) for effect
magnitudes that move the object by more than a tiny model's own error; everything else in the world
stays the default one the model was trained in. ``--frames N`` sets the generated episodes' length
(the tiny preset's 40 frames by default): the same motions, slower, so an effect has longer to act.

World effect -> registry names that count as a match: wind -> wind; air_drag -> linear_drag or
quadratic_drag; table_friction -> table_friction; slip -> gripper_slip; heavy -> mass_scale;
stiff -> (no term in the library: any name is a miss); none -> none.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

EXPECTED = {"wind": {"wind"}, "air_drag": {"linear_drag", "quadratic_drag"}, "table_friction": {"table_friction"},
            "slip": {"gripper_slip"}, "heavy": {"mass_scale"}, "stiff": {"stiffness_scale"}, "none": {"none"}}


def hidden_effects(data: Path) -> list[str]:
    """The effects switched on in a reference-world dataset, from its evaluation sidecars (scoring only)."""
    names: set[str] = set()
    found = False
    for meta in sorted(Path(data).glob("*.meta.json")):
        found = True
        names |= set(json.loads(meta.read_text()).get("effects", {}) or {})
    if not found:
        raise FileNotFoundError(f"{data}: no *.meta.json sidecars (not reference-world data?)")
    return sorted(names) or ["none"]


METRICS = ("rmse", "chamfer")


def _ratio(after, before):
    return None if (after is None or before is None or not before > 0) else after / before


def score_gap(gap_before: dict, gap_after: dict, floor: dict | None, metrics=METRICS) -> dict:
    """Shrink of the held-out gap, raw and effect-attributable (see the module docstring).

    ``floor``: the unchanged model's metrics on the effect-free twin data (None: unknown).
    Per metric m: ``ratio_<m>`` = after / before (raw); ``excess_before_<m>`` / ``excess_after_<m>`` =
    before / after minus the floor; ``ratio_excess_<m>`` = excess_after / excess_before (None unless
    excess_before > 0: an effect that does not raise the metric above the floor has no excess to
    shrink). ``halved_raw`` / ``halved_excess``: the ratio <= 0.5 on every metric (None where a ratio is
    undefined).
    """
    row: dict = {}
    for m in metrics:
        b, a = gap_before.get(m), gap_after.get(m)
        fl = None if floor is None else floor.get(m)
        row[f"ratio_{m}"] = _ratio(a, b)
        row[f"floor_{m}"] = fl
        eb = None if (b is None or fl is None) else b - fl
        ea = None if (a is None or fl is None) else a - fl
        row[f"excess_before_{m}"], row[f"excess_after_{m}"] = eb, ea
        row[f"ratio_excess_{m}"] = _ratio(ea, eb)

    def halved(prefix):
        rs = [row[f"{prefix}_{m}"] for m in metrics]
        return None if any(r is None for r in rs) else all(r <= 0.5 for r in rs)

    row["halved_raw"] = halved("ratio")
    row["halved_excess"] = halved("ratio_excess")
    return row


def order_effects(effects: list[str]) -> list[str]:
    """``none`` (the negative control, whose gap_before is the floor) first, the rest in the given order."""
    return (["none"] if "none" in effects else []) + [e for e in effects if e != "none"]


def format_table(rows: list[dict], header: str) -> list[str]:
    """The markdown lines of OUT/table.md."""
    f = lambda v: "n/a" if v is None else f"{v:.4f}"  # noqa: E731
    g = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
    yn = lambda v: "n/a" if v is None else ("yes" if v else "no")  # noqa: E731
    lines = [header, "",
             "Gap = held-out depth RMSE / Chamfer (m) of the model before → after the workflow's change. "
             "**raw**: after / before on the effect data. **excess** (effect-attributable): "
             "(after − floor) / (before − floor), floor = the unchanged model on the effect-free twin data "
             "(the `none` row's before). *halved* = ratio ≤ 0.5 on both RMSE and Chamfer.", "",
             "**detected**: the measured episodes' 3D residuals exceed the reference episodes' (the model's own "
             "error) with the workflow's confidence (AUC = P(measured > reference), its lower bound > 0.5), named "
             "or not.", "",
             "| hidden | named | match | detected (AUC, bound) | top explained (±std) [+ wrist load = score] | runner-up | RMSE before → after (floor) | "
             "Chamfer before → after (floor) | raw ratio RMSE / Chamfer | halved (raw) | "
             "excess RMSE before → after | excess Chamfer before → after | excess ratio RMSE / Chamfer | halved (excess) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    def cand(row, std: bool) -> str:  # "name +explained[±std][ + load = score]" (the load where the workflow had it)
        if row is None:
            return ""
        txt = row["name"] + " " + format(row["explained_fraction"], "+.3f")
        txt += ("±" + format(row["uncertainty"], ".3f")) if std else ""
        if "load_explained" in row:
            txt += f" + load {max(row['load_explained'], -1.0):+.3f} = {row['score']:+.3f}"
        return txt

    for r in rows:
        rk = r.get("ranking") or []
        top, second = (rk[0] if rk else None), (rk[1] if len(rk) > 1 else None)
        gb, ga = r["gap_before"], r["gap_after"]
        det = r.get("detection") or {}
        dtxt = ("n/a" if not det.get("assessed") else
                f"{'yes' if det['detected'] else 'no'} ({det['auc']:.2f}, {det['auc_low']:.2f})")
        lines.append(
            f"| {','.join(r['hidden'])} | {r['named']} | {'yes' if r['match'] else 'NO'} | {dtxt} | "
            f"{cand(top, True)} | {cand(second, False)} | "
            f"{f(gb.get('rmse'))} → {f(ga.get('rmse'))} ({f(r.get('floor_rmse'))}) | "
            f"{f(gb.get('chamfer'))} → {f(ga.get('chamfer'))} ({f(r.get('floor_chamfer'))}) | "
            f"{g(r.get('ratio_rmse'))} / {g(r.get('ratio_chamfer'))} | {yn(r.get('halved_raw'))} | "
            f"{f(r.get('excess_before_rmse'))} → {f(r.get('excess_after_rmse'))} | "
            f"{f(r.get('excess_before_chamfer'))} → {f(r.get('excess_after_chamfer'))} | "
            f"{g(r.get('ratio_excess_rmse'))} / {g(r.get('ratio_excess_chamfer'))} | {yn(r.get('halved_excess'))} |")
    return lines


def load_world(world_config: str | None = None, effects_config: str | None = None, frames: int | None = None):
    """The world config (default: config/world/default.yaml) with its effect magnitudes replaced by
    ``effects_config`` (a YAML path or a name in config/world) when given, and the ``tiny`` preset's
    episode length set to ``frames`` (the same motions, slower: an effect has longer to act)."""
    from soma_ros.world import load_effects_config, load_world_config

    cfg = load_world_config(world_config) if world_config else load_world_config()
    if effects_config:
        cfg.effects = load_effects_config(effects_config)  # resolves names in config/world
    if frames is not None:
        if int(frames) < 2:
            raise ValueError(f"frames must be at least 2, got {frames}")
        cfg.presets["tiny"].frames = [int(frames), int(frames)]
    cfg.validate()
    return cfg


def _generate(obj: str, out: Path, episodes: int, seed: int, effect: str, world_config: str | None, log,
              effects_config: str | None = None, frames: int | None = None) -> Path:
    from soma_ros.world import generate_dataset

    if (out / "manifest.json").is_file():
        if frames is not None:
            from soma_ros.data.dataset import load_manifest

            have = sorted({e.get("frames") for e in load_manifest(out)["episodes"]})
            if have != [int(frames)]:
                raise ValueError(f"{out}: existing data has episodes of {have} frames, not {frames} "
                                 f"(another --out, or delete it to regenerate)")
        log(f"data: reusing {out}")
        return out
    cfg = load_world(world_config, effects_config, frames)
    t0 = time.time()
    generate_dataset(cfg, obj, "tiny", out, episodes=episodes, seed=seed,
                     effects=None if effect == "none" else [effect], progress=False)
    log(f"data: generated {out} ({episodes} episodes, effect {effect}, {time.time() - t0:.0f} s)")
    return out


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MUJOCO_GL", "egl")
    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))
    from soma_ros.core.checkpoint import read_checkpoint
    from soma_ros.discrepancy.workflow import load_discrepancy_config, run_discrepancy

    log = lambda s: print(s, flush=True)  # noqa: E731
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    unknown = [e for e in effects if e not in EXPECTED]
    if unknown:
        print(f"benchmarks.discrepancy: error: unknown effect(s) {unknown} (known: {', '.join(EXPECTED)})", file=sys.stderr)
        return 2
    if not args.no_negative and "none" not in effects:
        effects.append("none")
    effects = order_effects(effects)  # the floor (gap_before on `none`) before the effects it is subtracted from
    # ---- 1. the model, trained on effect-free data
    if args.run:
        run_dir = Path(args.run)
        extra = read_checkpoint(run_dir / "checkpoint.pt")["extra"]
        log(f"model: reusing {run_dir} (trained on {extra.get('dataset')})")
    else:
        from soma_ros.training.config import load_train_config
        from soma_ros.training.train import train

        clean = _generate(args.object, out / "data" / f"{args.object}_none", args.episodes, args.seed, "none",
                          args.world_config, log, args.effects_config, args.frames)
        run_dir = out / "run"
        if not (run_dir / "checkpoint.pt").is_file() or not read_checkpoint(run_dir / "checkpoint.pt")["extra"].get("complete"):
            tcfg = load_train_config(args.train_config, {"object": args.object})
            train(tcfg, clean, run_dir, log=log)
    over = {}
    if args.reference_episodes > 0:
        # the own-error control's reference: new effect-free episodes (another world seed), which the
        # model was not trained on -- what a user records under the model's known conditions
        ref = _generate(args.object, out / "data" / f"{args.object}_reference", args.reference_episodes,
                        args.seed + 1, "none", args.world_config, log, args.effects_config, args.frames)
        over["reference_data"] = str(ref)
        over["reference_episodes"] = args.reference_episodes  # all of them (the config's default picks 12)
    over["jobs"] = args.jobs
    cfg = load_discrepancy_config(args.config, over)
    rows = []
    floor = None
    for eff in effects:
        data = _generate(args.object, out / "data" / f"{args.object}_{eff}", args.episodes, args.seed, eff,
                         args.world_config, log, args.effects_config, args.frames)
        t0 = time.time()
        rep = run_discrepancy(run_dir / "checkpoint.pt", data, out / eff, cfg, log=log)
        hidden = hidden_effects(data)
        want = set().union(*(EXPECTED.get(h, set()) for h in hidden))
        gb, ga = rep["gap_before"], rep["gap_after"]
        if hidden == ["none"] and floor is None:
            floor = dict(gb)
        row = {"hidden": hidden, "named": rep["named_effect"], "match": rep["named_effect"] in want,
               "ranking": rep["ranking"], "detection": rep.get("discrepancy"), "gap_before": gb, "gap_after": ga,
               **score_gap(gb, ga, floor),
               "seconds": round(time.time() - t0, 1)}
        row["halved"] = bool(row["halved_raw"])  # the old key (raw definition), kept for readers of bench.json
        rows.append(row)
        log(f"[{eff}] hidden {hidden} named {row['named']} match {row['match']} "
            f"raw rmse x{row['ratio_rmse']} chamfer x{row['ratio_chamfer']}; "
            f"excess rmse x{row['ratio_excess_rmse']} chamfer x{row['ratio_excess_chamfer']}")
    header = (f"# Discrepancy benchmark\n\nmodel: `{run_dir}`; object {args.object}; seed {args.seed}; "
              f"{args.episodes} episodes per dataset; workflow config `{args.config}`; world config "
              f"`{args.world_config or 'default'}`; effect magnitudes `{args.effects_config or 'from the world config'}`; "
              f"{args.frames or 'preset'} frames per episode")
    lines = format_table(rows, header)
    (out / "table.md").write_text("\n".join(lines) + "\n")
    (out / "bench.json").write_text(json.dumps({"rows": rows, "floor": floor, "run": str(run_dir), "object": args.object,
                                                "seed": args.seed, "episodes": args.episodes,
                                                "world_config": args.world_config, "effects_config": args.effects_config,
                                                "frames": args.frames,
                                                "config": args.config, "reference_episodes": args.reference_episodes,
                                                "definitions": {
                                                    "ratio_<m>": "raw: gap_after / gap_before on the effect data",
                                                    "ratio_excess_<m>": "(gap_after - floor) / (gap_before - floor); floor = "
                                                                        "gap_before on the effect-free twin data (`none`)",
                                                    "halved_raw": "ratio_rmse <= 0.5 and ratio_chamfer <= 0.5",
                                                    "halved_excess": "ratio_excess_rmse <= 0.5 and ratio_excess_chamfer <= 0.5",
                                                    "halved": "= halved_raw (old key)"}}, indent=1))
    print("\n".join(lines))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.discrepancy", description=__doc__.splitlines()[0])
    p.add_argument("--object", default="rope", choices=["rope", "cloth", "doll"])
    p.add_argument("--effects", default="wind,table_friction,slip", metavar="LIST",
                   help="hidden effects to test, one per measured dataset (default: wind,table_friction,slip)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--run", default=None, metavar="RUN", help="reuse a trained run folder (else train on effect-free data)")
    p.add_argument("--train-config", default="tiny", metavar="NAME|YAML")
    p.add_argument("--config", default="default", metavar="NAME|YAML", help="workflow config (config/discrepancy)")
    p.add_argument("--episodes", type=int, default=10, metavar="N")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="world seed (the same for clean and measured data)")
    p.add_argument("--world-config", default=None, metavar="YAML", help="world config (default: config/world/default.yaml)")
    p.add_argument("--effects-config", default=None, metavar="NAME|YAML",
                   help="effect magnitudes replacing the world config's (a name in config/world, e.g. effects_discrepancy)")
    p.add_argument("--frames", type=int, default=None, metavar="N",
                   help="frames per generated episode (default: the world's tiny preset, 40 at 30 fps); the same "
                        "motions, slower, so an effect has longer to act")
    p.add_argument("--no-negative", action="store_true", help="skip the negative control (no effect)")
    p.add_argument("--jobs", type=int, default=1, metavar="N",
                   help="candidates fitted in N worker processes (the workflow's `jobs`; results do not depend on it)")
    p.add_argument("--reference-episodes", type=int, default=12, metavar="N",
                   help="effect-free episodes recorded with world seed + 1 as the workflow's own-error reference "
                        "(0: the workflow's default, the model's training dataset outside its train split)")
    args = p.parse_args(argv)
    try:
        return run(args)
    except (ValueError, FileNotFoundError) as e:  # bad world/effects config, data of another length, ...
        print(f"benchmarks.discrepancy: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
