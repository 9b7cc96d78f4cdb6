"""Discrepancy benchmark (issue #8): hide one effect in measured data and check the workflow names it.

    python -m benchmarks.discrepancy --object rope --effects wind,table_friction,slip --out DIR
    python -m benchmarks.discrepancy --object rope --effects wind --run RUN --out DIR   # reuse a trained run

1. A model trained on effect-free reference-world data (``--run`` reuses one; else OUT/data/<obj>_none
   is generated and ``soma train`` runs with ``--train-config``, default tiny).
2. For every hidden effect (and ``none``, the negative control, unless ``--no-negative``): measured data
   from the same world and seed with that effect switched on (OUT/data/<obj>_<effect>).
3. The workflow (:func:`trainer.discrepancy.run_discrepancy`) on it -> OUT/<effect>/report.{md,json}.
4. Scoring (the benchmark, not the workflow, reads the evaluation sidecars ``<episode>.meta.json``
   to learn which effect is on): OUT/table.md and OUT/bench.json with, per hidden effect, the named
   effect, whether it matches, the explained fractions and the held-out gap before/after (depth RMSE,
   Chamfer) with the shrink factor (acceptance: named correctly and after <= 0.5 x before on both).

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
            "slip": {"gripper_slip"}, "heavy": {"mass_scale"}, "stiff": set(), "none": {"none"}}


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


def _generate(obj: str, out: Path, episodes: int, seed: int, effect: str, world_config: str | None, log) -> Path:
    from soma_ros.world import generate_dataset, load_world_config

    if (out / "manifest.json").is_file():
        log(f"data: reusing {out}")
        return out
    cfg = load_world_config(world_config) if world_config else load_world_config()
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
    from trainer.discrepancy import load_discrepancy_config, run_discrepancy

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
    # ---- 1. the model, trained on effect-free data
    if args.run:
        run_dir = Path(args.run)
        extra = read_checkpoint(run_dir / "checkpoint.pt")["extra"]
        log(f"model: reusing {run_dir} (trained on {extra.get('dataset')})")
    else:
        from trainer.config import load_train_config
        from trainer.train import train

        clean = _generate(args.object, out / "data" / f"{args.object}_none", args.episodes, args.seed, "none",
                          args.world_config, log)
        run_dir = out / "run"
        if not (run_dir / "checkpoint.pt").is_file() or not read_checkpoint(run_dir / "checkpoint.pt")["extra"].get("complete"):
            tcfg = load_train_config(args.train_config, {"object": args.object})
            train(tcfg, clean, run_dir, log=log)
    cfg = load_discrepancy_config(args.config)
    rows = []
    for eff in effects:
        data = _generate(args.object, out / "data" / f"{args.object}_{eff}", args.episodes, args.seed, eff,
                         args.world_config, log)
        t0 = time.time()
        rep = run_discrepancy(run_dir / "checkpoint.pt", data, out / eff, cfg, log=log)
        hidden = hidden_effects(data)
        want = set().union(*(EXPECTED.get(h, set()) for h in hidden))
        gb, ga = rep["gap_before"], rep["gap_after"]

        def shrink(m):
            b, a = gb.get(m), ga.get(m)
            return None if (a is None or not b) else a / b

        row = {"hidden": hidden, "named": rep["named_effect"], "match": rep["named_effect"] in want,
               "ranking": rep["ranking"], "gap_before": gb, "gap_after": ga,
               "ratio_rmse": shrink("rmse"), "ratio_chamfer": shrink("chamfer"), "seconds": round(time.time() - t0, 1)}
        row["halved"] = (row["ratio_rmse"] is not None and row["ratio_rmse"] <= 0.5 and row["ratio_chamfer"] is not None
                         and row["ratio_chamfer"] <= 0.5)
        rows.append(row)
        log(f"[{eff}] hidden {hidden} named {row['named']} match {row['match']} "
            f"rmse x{row['ratio_rmse']} chamfer x{row['ratio_chamfer']}")
    lines = ["# Discrepancy benchmark", "", f"model: `{run_dir}`; object {args.object}; seed {args.seed}; "
             f"{args.episodes} episodes per dataset; workflow config `{args.config}`", "",
             "| hidden | named | match | top explained (±std) | runner-up | RMSE before → after | Chamfer before → after | halved both |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        top, second = r["ranking"][0], (r["ranking"][1] if len(r["ranking"]) > 1 else None)
        f = lambda v: "n/a" if v is None else f"{v:.4f}"  # noqa: E731
        lines.append(
            f"| {','.join(r['hidden'])} | {r['named']} | {'yes' if r['match'] else 'NO'} | "
            f"{top['name']} {top['explained_fraction']:+.3f}±{top['uncertainty']:.3f} | "
            f"{'' if second is None else second['name'] + ' ' + format(second['explained_fraction'], '+.3f')} | "
            f"{f(r['gap_before'].get('rmse'))} → {f(r['gap_after'].get('rmse'))} | "
            f"{f(r['gap_before'].get('chamfer'))} → {f(r['gap_after'].get('chamfer'))} | {'yes' if r['halved'] else 'no'} |")
    (out / "table.md").write_text("\n".join(lines) + "\n")
    (out / "bench.json").write_text(json.dumps({"rows": rows, "run": str(run_dir), "object": args.object,
                                                "seed": args.seed, "episodes": args.episodes}, indent=1))
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
    p.add_argument("--world-config", default=None, metavar="YAML", help="world config (e.g. other effect magnitudes)")
    p.add_argument("--no-negative", action="store_true", help="skip the negative control (no effect)")
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
