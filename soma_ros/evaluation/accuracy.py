"""`soma bench accuracy`: the form of the paper's Table 1 on reference-world data.

For every object (rope, cloth, doll) one command

1. **data**: generates a reference-world dataset (``soma world``; or reuses the one
   already in ``OUT/data/<object>_<preset>`` if its manifest matches),
2. **trains** every learned variant on the training episodes with ``soma train``
   (:func:`soma_ros.training.train.train`): ``full``, ``state_only``, ``img_only``, ``no_mrt``
   (:mod:`soma_ros.evaluation.baselines` defines them; :func:`variant_train_config` the
   config differences); all share the scene set up by ``full`` (same G_0, table,
   hierarchy), so every variant starts every episode from the same state,
3. **fits** the ``spring_mass`` baseline's parameters on the same training bags,
4. **evaluates** every variant and ``static`` on the training episodes
   (resimulation) and the held-out episodes (generalization) with
   :func:`soma_ros.evaluation.evaluate.evaluate_models`,
5. **writes** ``OUT/table.json`` ``{object: {variant: {split: {metric: value}}}}``,
   ``OUT/table.md`` (one table per object: Resimulation | Generalization x Abs Rel,
   RMSE, PSNR, SSIM, LPIPS, Chamfer, plus by how much ``full`` beats ``static`` and
   ``state_only`` on held-out RMSE and PSNR), ``OUT/bench.json`` (timings, settings,
   machine) and per-variant reports under ``OUT/eval/<object>/<split>/<variant>/``.

Every number in the tables is measured in that run. Re-running the command
with the same OUT reuses finished steps (a dataset with a matching manifest, a
complete training run -- an interrupted one resumes --, a fitted spring-mass
model) and recomputes the evaluation; a dataset that does not match the preset
is regenerated and the runs trained on it are deleted; ``--fresh`` starts over.

Presets live in ``config/eval/<preset>.yaml`` (:class:`BenchConfig`): ``tiny``
runs on a 2-core CPU (docs/evaluation.md gives the time per object), ``paper`` is the paper's scale
for a GPU.
"""

from __future__ import annotations

import copy
import dataclasses
import fcntl
import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import torch
import yaml

from soma_ros.core.config import ConfigError, from_dict, load_object_config, read_config, to_dict
from soma_ros.core.machine import machine_info
from soma_ros.core.spring_mass import SpringMassConfig
from soma_ros.paths import resolve_config

from soma_ros.evaluation.baselines import (
    SPRING_MASS_FILE,
    VARIANTS,
    SpringMassFitConfig,
    StaticModel,
    fit_spring_mass,
    load_model,
    save_spring_mass,
)
from soma_ros.training.config import TrainConfig, load_train_config
from soma_ros.evaluation.evaluate import EvalConfig, EvalContext, METRIC_LABELS, evaluate_models, format_metric
from soma_ros.core.scoring import EXTRA_METRICS, METRICS, EvalMetricsConfig

__all__ = [
    "OBJECTS",
    "TRAINED_VARIANTS",
    "WorldSection",
    "TrainSection",
    "BenchConfig",
    "load_bench_config",
    "variant_train_config",
    "run_bench",
    "table_markdown",
    "comparison",
    "task_means",
    "prior_comparison",
]

OBJECTS = ("rope", "cloth", "doll")
#: variants that `soma train` trains (the others: static needs nothing, spring_mass is fitted here)
TRAINED_VARIANTS = ("full", "state_only", "img_only", "no_mrt")
SPLITS = ("train", "test")
SPLIT_LABEL = {"train": "Resimulation", "test": "Generalization"}


@dataclass
class WorldSection:
    """Reference-world data per object: ``soma world --preset PRESET --episodes N --seed S``."""

    preset: str = "tiny"
    episodes: int = 6
    seed: int = 0
    frames: Optional[int] = None

    def validate(self) -> None:
        if self.episodes < 2:
            raise ConfigError(f"world.episodes: need >= 2 (train and held-out), got {self.episodes}")


@dataclass
class TrainSection:
    """``config``: the train config every learned variant starts from (``config/train/<name>``);
    ``overrides``: merged over it for every variant (the variant's own differences are applied
    after, see :func:`variant_train_config`); ``effect_params``: per object, parameters of the
    model's effects to change, ``{object: {effect name: {param: value}}}``."""

    config: str = "tiny"
    overrides: dict = field(default_factory=dict)
    effect_params: dict = field(default_factory=dict)


@dataclass
class BenchConfig:
    """A preset of the accuracy benchmark (``config/eval/<preset>.yaml``)."""

    name: str = "tiny"
    objects: list[str] = field(default_factory=lambda: list(OBJECTS))
    variants: list[str] = field(default_factory=lambda: list(VARIANTS))
    world: WorldSection = field(default_factory=WorldSection)
    train: TrainSection = field(default_factory=TrainSection)
    spring_mass: dict = field(default_factory=dict)  # SpringMassFitConfig fields; model: SpringMassConfig fields
    eval: dict = field(default_factory=dict)  # EvalConfig fields (metrics: EvalMetricsConfig fields)

    def validate(self) -> "BenchConfig":
        bad = [o for o in self.objects if o not in OBJECTS]
        if bad:
            raise ConfigError(f"objects: unknown {bad} (known: {', '.join(OBJECTS)})")
        badv = [v for v in self.variants if v not in VARIANTS]
        if badv:
            raise ConfigError(f"variants: unknown {badv} (known: {', '.join(VARIANTS)})")
        if "full" not in self.variants:
            raise ConfigError("variants: 'full' is required (its scene is shared by every variant)")
        self.world.validate()
        self.spring_mass_config(0.1)
        self.eval_config()
        return self

    def spring_mass_config(self, total_mass: float) -> SpringMassFitConfig:
        d = copy.deepcopy(self.spring_mass)
        model = dict(d.pop("model", {}) or {})
        model.setdefault("total_mass", float(total_mass))
        fc = from_dict(SpringMassFitConfig, d, "spring_mass.")
        fc.model = from_dict(SpringMassConfig, model, "spring_mass.model.")
        return fc.validate()

    def eval_config(self) -> EvalConfig:
        d = copy.deepcopy(self.eval)
        metrics = dict(d.pop("metrics", {}) or {})
        ec = from_dict(EvalConfig, d, "eval.")
        ec.metrics = from_dict(EvalMetricsConfig, metrics, "eval.metrics.")
        return ec.validate()


def load_bench_config(preset: str | Path) -> BenchConfig:
    """``config/eval/<preset>.yaml`` (or a YAML path) -> :class:`BenchConfig`."""
    p = Path(preset)
    if not (p.suffix in (".yaml", ".yml") and p.is_file()):
        p = resolve_config(f"eval/{preset}")
    data = read_config(p)  # with its base applied
    data.setdefault("name", p.stem)
    return from_dict(BenchConfig, data, f"{p.name}: ").validate()


# --------------------------------------------------------------------------- variants
def _merge(base: dict, over: dict) -> dict:
    """Nested dict merge (mappings merged key by key, anything else replaced)."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def variant_train_config(bench: BenchConfig, obj: str, variant: str) -> TrainConfig:
    """The train config of a learned variant for one object.

    * ``full``: ``bench.train.config`` with ``bench.train.overrides``.
    * ``img_only``: the paper's "Img-only" (raw image supervision, without the blended
      supervision): the object-masked L2 + D-SSIM image loss is the only term --
      ``loss.momentum_weight = 0`` (no regulariser) and the 3D terms the base config adds
      (``points_weight``, ``depth_weight``) = 0. Keeping the 3D point
      term would make it ``full`` minus a regulariser that is ~0 anyway, not an image-only model.
    * ``no_mrt``: + no multi-resolution schedule: stage 1 off, all its epochs at the frame rate
      in stage 2 (same number of iterations).
    * ``state_only``: + the model's effects without ``robot``, plus ``wind`` (a learnable constant
      acceleration field: the autonomous driving term; see :mod:`soma_ros.evaluation.baselines`).
    """
    if variant not in TRAINED_VARIANTS:
        raise ValueError(f"variant '{variant}' is not trained by `soma train` (trained: {', '.join(TRAINED_VARIANTS)})")
    base = _merge(bench.train.overrides, {"object": obj, "name": f"{bench.name}_{obj}_{variant}"})
    cfg = load_train_config(bench.train.config, overrides=base)
    changes = bench.train.effect_params.get(obj) or {}
    if changes:
        effects = [e.to_yaml_dict() for e in cfg.model_config().effects]
        missing = set(changes) - {e["name"] for e in effects}
        if missing:
            raise ConfigError(f"train.effect_params.{obj}: the model has no effect {', '.join(sorted(missing))}")
        effects = [_merge(e, changes.get(e["name"], {})) for e in effects]
        base = _merge(base, {"model_overrides": {"effects": effects}})
        cfg = load_train_config(bench.train.config, overrides=base)
    if variant == "full":
        return cfg
    if variant == "img_only":
        over: dict[str, Any] = {"loss": {"momentum_weight": 0.0, "points_weight": 0.0, "depth_weight": 0.0}}
    elif variant == "no_mrt":
        s = cfg.schedule
        over = {"schedule": {"stage1": {"epochs": 0}, "stage2": {"epochs": s.stage1.epochs + s.stage2.epochs}}}
    else:  # state_only
        effects = [e.to_yaml_dict() for e in cfg.model_config().effects if e.name != "robot"]
        if not any(e["name"] == "wind" for e in effects):
            effects.append({"name": "wind"})
        over = {"model_overrides": {"effects": effects}}
    return load_train_config(bench.train.config, overrides=_merge(base, over))


def _check_no_test_selection(cfg: TrainConfig, what: str) -> None:
    """The benchmark scores the manifest's ``test`` split: no run may train or select its checkpoint on it."""
    d = cfg.data
    if d.train_split == "test" or (d.val_split == "test" and cfg.run.keep != "last") or \
            (d.val_split is not None and d.val_split == d.train_split):
        raise ConfigError(f"{what}: data.train_split={d.train_split!r}, data.val_split={d.val_split!r}, "
                          f"run.keep={cfg.run.keep!r}: the held-out test episodes would train or select the model; "
                          "use data.val_split: null (validation episodes held out of the training split)")


# --------------------------------------------------------------------------- steps
def _dataset(bench: BenchConfig, obj: str, folder: Path, log, progress: bool) -> dict:
    """Reuse ``folder`` if its manifest matches the preset (object, preset, seed, episodes, frames,
    no effects, every bag present), else (re)generate it. ``reused: False`` means every run
    trained on the folder's former content is stale."""
    w = bench.world
    man = folder / "manifest.json"
    if man.is_file():
        m = json.loads(man.read_text())
        ok = (m.get("object") == obj and m.get("preset") == w.preset and int(m.get("seed", -1)) == w.seed
              and len(m.get("episodes", [])) == w.episodes and not m.get("effects")
              and all((folder / e["bag"]).exists() for e in m["episodes"])
              and (w.frames is None or all(int(e.get("frames", -1)) == w.frames for e in m["episodes"])))
        if ok:
            log(f"[{obj}] data: reusing {folder} ({w.episodes} episodes)")
            return {"reused": True, "seconds": 0.0}
        log(f"[{obj}] data: {folder} holds another or an unfinished dataset: regenerating it")
    if folder.exists():
        shutil.rmtree(folder)
    from soma_ros.world import generate_dataset, load_world_config

    t0 = time.time()
    log(f"[{obj}] data: generating {w.episodes} '{w.preset}' episodes (seed {w.seed}) into {folder}")
    generate_dataset(load_world_config(), obj, w.preset, folder, episodes=w.episodes, seed=w.seed, frames=w.frames,
                     progress=progress)
    return {"reused": False, "seconds": round(time.time() - t0, 1)}


def _checkpoint_complete(run: Path) -> bool:
    ck = run / "checkpoint.pt"
    if not ck.is_file():
        return False
    from soma_ros.core.checkpoint import read_checkpoint

    try:
        return bool(read_checkpoint(ck)["extra"].get("complete"))
    except ValueError:
        return False


def _train_variant(cfg: TrainConfig, obj: str, variant: str, data: Path, run: Path, scene: Optional[Path],
                   log, progress: bool) -> dict:
    from soma_ros.training.train import train

    cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, progress=progress))
    def info(summary: dict) -> dict:
        return {"val_loss_untrained": summary.get("val_loss_untrained"),
                "val_loss": summary.get("val_loss"), "iterations": summary.get("iterations"),
                "best_val_loss": summary.get("best_val_loss"), "best_iteration": summary.get("best_iteration"),
                "kept": summary.get("kept"), "train_episodes": summary.get("train_episodes"),
                "val_episodes": summary.get("val_episodes")}

    if _checkpoint_complete(run):
        log(f"[{obj}] {variant}: reusing the complete run {run}")
        try:  # the reused run's own training record
            summary = json.loads((run / "summary.json").read_text())
        except (OSError, ValueError):
            summary = {}
        return {"reused": True, "seconds": 0.0, "training_seconds": summary.get("seconds"), **info(summary)}
    t0 = time.time()
    log(f"[{obj}] {variant}: training ({cfg.schedule.total_iters} iterations) into {run}")
    summary = train(cfg, data, run, scene_dir=scene, log=lambda s: log(f"[{obj}] {variant}: {s}"))
    return {"reused": False, "seconds": round(time.time() - t0, 1), **info(summary)}


def _copy_context(src_run: Path, dst: Path) -> None:
    """Give a baseline folder the scene and train config of the run it shares (so that
    ``soma eval --checkpoint DST`` finds them)."""
    dst.mkdir(parents=True, exist_ok=True)
    shutil.copy2(src_run / "train_config.yaml", dst / "train_config.yaml")
    if (dst / "scene").exists():
        shutil.rmtree(dst / "scene")
    shutil.copytree(src_run / "scene", dst / "scene")


def _fit_spring_mass(bench: BenchConfig, obj: str, ctx: EvalContext, full_run: Path, out: Path, log,
                     progress: bool) -> dict:
    path = out / SPRING_MASS_FILE
    if path.is_file():
        log(f"[{obj}] spring_mass: reusing {path}")
        try:
            info = json.loads((out / "fit.json").read_text())
            return {"reused": True, "seconds": 0.0, "parameters": info["parameters"],
                    "train_loss": info["loss_final_all_train"]}
        except (OSError, ValueError, KeyError):
            return {"reused": True, "seconds": 0.0}
    fc = bench.spring_mass_config(load_object_config(obj).total_mass)
    names = [r.name for r in ctx.episodes("train")]
    log(f"[{obj}] spring_mass: fitting its 5 parameters on "
        f"{len(names)} training episodes ({fc.iters} iterations)")
    t0 = time.time()
    model, info = fit_spring_mass(((ctx.store.episode(n), ctx.store.initial_splats(n)) for n in names), ctx.scene, fc,
                                  progress=progress, log=lambda s: log(f"[{obj}] {s}"))
    _copy_context(full_run, out)
    save_spring_mass(path, model, info)
    (out / "fit.json").write_text(json.dumps(info, indent=1))
    return {"reused": False, "seconds": round(time.time() - t0, 1), "parameters": info["parameters"],
            "train_loss": info["loss_final_all_train"]}


# --------------------------------------------------------------------------- tables
def comparison(table: dict, obj: str, split: str = "test") -> list[dict]:
    """How ``full`` compares with ``static`` and ``state_only`` on RMSE and PSNR of a split:
    [{"baseline", "metric", "full", "baseline_value", "delta" (full - baseline), "full_better"}]."""
    rows = []
    t = table.get(obj, {})
    if "full" not in t:
        return rows
    for base in ("static", "state_only"):
        if base not in t:
            continue
        for m in ("rmse", "psnr"):
            f, b = t["full"][split].get(m), t[base][split].get(m)
            if f is None or b is None or (isinstance(f, float) and math.isnan(f)) or (isinstance(b, float) and math.isnan(b)):
                continue
            better = f < b if m == "rmse" else f > b
            rows.append({"baseline": base, "metric": m, "full": f, "baseline_value": b, "delta": f - b,
                         "relative": (f - b) / abs(b) if b else math.nan, "full_better": bool(better)})
    return rows


#: metrics of the full vs prior_only comparison (lower is better for both)
PRIOR_METRICS = ("rmse", "chamfer")


def task_means(episodes: dict[str, dict], metrics: Sequence[str] = METRICS) -> dict[str, dict]:
    """{task: {metric: mean over that task's episodes (NaN-safe), "episodes": count}} from an
    evaluation's per-episode results (each with its ``task``; None counts as ``"-"``)."""
    out: dict[str, dict] = {}
    for task in dict.fromkeys((e.get("task") or "-") for e in episodes.values()):
        eps = [e for e in episodes.values() if (e.get("task") or "-") == task]
        row: dict = {}
        for m in metrics:
            vals = [float(e[m]) for e in eps if e.get(m) is not None and math.isfinite(float(e[m]))]
            row[m] = sum(vals) / len(vals) if vals else math.nan
        row["episodes"] = len(eps)
        out[task] = row
    return out


def prior_comparison(by_task: dict, split: str = "test", tolerance: float = 0.05) -> dict:
    """``full`` against ``prior_only`` on a split, per task and averaged over the tasks, on depth
    RMSE and Chamfer: {"tasks": {task: {metric: {"full", "prior_only", "relative"}}},
    "mean": {metric: {...}}, "full_better_on_mean": {metric: bool}, "worst_task_relative":
    {metric: largest (full - prior) / prior over the tasks}, "within_tolerance": every task's
    relative <= ``tolerance``} (empty without both variants)."""
    f, p = by_task.get("full", {}).get(split), by_task.get("prior_only", {}).get(split)
    if not f or not p:
        return {}
    tasks: dict = {}
    for task in f:
        if task not in p:
            continue
        tasks[task] = {}
        for m in PRIOR_METRICS:
            a, b = f[task].get(m, math.nan), p[task].get(m, math.nan)
            tasks[task][m] = {"full": a, "prior_only": b, "relative": (a - b) / abs(b) if b else math.nan}
    mean, better, worst = {}, {}, {}
    for m in PRIOR_METRICS:
        a = [tasks[t][m]["full"] for t in tasks if math.isfinite(tasks[t][m]["full"])]
        b = [tasks[t][m]["prior_only"] for t in tasks if math.isfinite(tasks[t][m]["prior_only"])]
        ma, mb = (sum(a) / len(a) if a else math.nan), (sum(b) / len(b) if b else math.nan)
        mean[m] = {"full": ma, "prior_only": mb, "relative": (ma - mb) / abs(mb) if mb else math.nan}
        better[m] = bool(ma < mb)
        rel = [tasks[t][m]["relative"] for t in tasks if math.isfinite(tasks[t][m]["relative"])]
        worst[m] = max(rel) if rel else math.nan
    return {"split": split, "tasks": tasks, "mean": mean, "full_better_on_mean": better,
            "worst_task_relative": worst, "tolerance": tolerance,
            "within_tolerance": all(math.isfinite(w) and w <= tolerance for w in worst.values())}


def prior_markdown(pc: dict) -> list[str]:
    """Lines of the full vs prior_only table (:func:`prior_comparison`)."""
    if not pc:
        return []
    lines = ["Held-out: full vs prior_only (full's kept weights, network off) per task", "",
             "| task | full RMSE | prior_only RMSE | rel. | full Chamfer | prior_only Chamfer | rel. |",
             "|---|---|---|---|---|---|---|"]
    for task, row in list(pc["tasks"].items()) + [("mean over tasks", pc["mean"])]:
        cells = []
        for m in PRIOR_METRICS:
            c = row[m]
            cells += [format_metric(m, c["full"]), format_metric(m, c["prior_only"]), f"{100 * c['relative']:+.1f} %"]
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    lines.append("")
    better = ", ".join(f"{m} {'yes' if pc['full_better_on_mean'][m] else 'NO'}" for m in PRIOR_METRICS)
    worst = ", ".join(f"{m} {100 * pc['worst_task_relative'][m]:+.1f} %" for m in PRIOR_METRICS)
    verdict = "met" if pc["within_tolerance"] else "NOT met"
    lines.append(f"- full better on the mean over tasks: {better}; worst task {worst} "
                 f"(target: <= {100 * pc['tolerance']:+.0f} %: {verdict})")
    lines.append("")
    return lines


def table_markdown(table: dict, bench: BenchConfig, meta: dict) -> str:
    """The Table-1-shaped markdown: per object, rows = variants, columns = split x metric."""
    lines = [f"# Accuracy benchmark ({bench.name} preset)", ""]
    lines.append(f"Reference world: {bench.world.episodes} episodes per object, preset '{bench.world.preset}', "
                 f"seed {bench.world.seed}; training config '{bench.train.config}'. Resimulation = training "
                 "episodes, Generalization = held-out episodes. Every number was measured in this run "
                 f"({meta.get('finished', '')}, {meta.get('wall_seconds', 0) / 60:.1f} min wall time).")
    if meta.get("command"):
        lines.append("")
        lines.append(f"Command: `{meta['command']}`")
    lines.append("")
    for obj, variants in table.items():
        split_eps = meta.get("objects", {}).get(obj, {}).get("episodes", {})
        om = meta.get("objects", {}).get(obj, {})
        lines.append(f"## {obj}  ({split_eps.get('train', '?')} train / {split_eps.get('test', '?')} held-out episodes; "
                     f"measured {om.get('finished', '?')} in {om.get('seconds', 0) / 60:.1f} min)")
        lines.append("")
        head = "| variant | " + " | ".join(f"{SPLIT_LABEL[s][:5]}. {METRIC_LABELS[m]}" for s in SPLITS for m in METRICS) + " |"
        lines.append(head)
        lines.append("|" + "---|" * (1 + len(SPLITS) * len(METRICS)))
        for v, splits in variants.items():
            cells = [format_metric(m, splits.get(s, {}).get(m)) for s in SPLITS for m in METRICS]
            lines.append(f"| {v} | " + " | ".join(cells) + " |")
        lines.append("")
        steps = om.get("steps", {})
        trained = []
        val_eps = None
        for v in TRAINED_VARIANTS:
            st = steps.get(v, {})
            if st.get("val_loss") is not None and st.get("val_loss_untrained") is not None:
                txt = f"{v} {st['val_loss_untrained']:.4f} -> {st['val_loss']:.4f} ({st.get('iterations')} it)"
                if st.get("kept") in ("best", "best_points", "best_score") and st.get("best_iteration") is not None:
                    txt += f", kept it {st['best_iteration']} ({st['best_val_loss']:.4f})"
                trained.append(txt)
                val_eps = val_eps or st.get("val_episodes")
        if trained:
            lines.append("Training (validation loss of `soma train` -- each variant's own objective without the "
                         "regulariser, so not comparable across variants --, untrained -> last; the checkpoint kept "
                         "and scored is the best by validation" + (f", on training-split episodes {', '.join(val_eps)}"
                                                                  " that no gradient step used" if val_eps else "")
                         + "): " + "; ".join(trained) + ".")
            lines.append("")
        sm = steps.get("spring_mass", {})
        if sm.get("parameters"):
            lines.append("spring_mass fitted parameters: " + ", ".join(f"{k} {v:.3g}" for k, v in sm["parameters"].items())
                         + f" (training loss {sm.get('train_loss', float('nan')):.4f} m).")
            lines.append("")
        comp = comparison(table, obj)
        if comp:
            lines.append("Held-out (generalization): full vs baselines")
            lines.append("")
            for c in comp:
                unit = " m" if c["metric"] == "rmse" else " dB"
                verdict = "full better" if c["full_better"] else "full NOT better"
                lines.append(f"- {c['metric'].upper()}: full {format_metric(c['metric'], c['full'])} vs {c['baseline']} "
                             f"{format_metric(c['metric'], c['baseline_value'])}: delta {c['delta']:+.4f}{unit} "
                             f"({100 * c['relative']:+.1f} %) -> {verdict}")
            un = om.get("depth_union", {})
            if un:
                lines.append("- depth RMSE over the union of measured and rendered object (reported, not the "
                             "headline: soma_ros/core/scoring.py): " + ", ".join(
                                 f"{v} {format_metric('rmse', un[v].get('test', {}).get('rmse_union'))}"
                                 for v in ("full", "static", "state_only") if v in un))
            lines.append("")
        lines += prior_markdown(om.get("prior_test", {}))
    lines.append("Metrics: " + "; ".join(f"{k}: {v}" for k, v in meta.get("protocol", {}).items()))
    lines.append("")
    return "\n".join(lines)


def _command_line() -> str:
    """How this process was started, as a person would type it."""
    prog = Path(sys.argv[0]).name if sys.argv else ""
    args = " ".join(sys.argv[1:])
    if prog == "bench_accuracy.py":
        return f"python -m benchmarks.bench_accuracy {args}"
    if prog in ("soma", "cli.py"):
        return f"soma {args}"
    return " ".join(sys.argv)


def _json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


# --------------------------------------------------------------------------- the benchmark
def run_bench(bench: BenchConfig, out: Path, objects: Optional[Sequence[str]] = None, fresh: bool = False,
              progress: bool = True, log: Callable[[str], None] = print) -> dict:
    """Run the whole benchmark into ``out``; returns {"table": ..., "meta": ...}."""
    from soma_ros.evaluation.evaluate import PROTOCOL

    t_start = time.time()
    out = Path(out)
    objects = list(objects or bench.objects)
    bad = [o for o in objects if o not in OBJECTS]
    if bad:
        raise ValueError(f"unknown object(s) {bad} (known: {', '.join(OBJECTS)})")
    if fresh and out.exists():
        for sub in ("data", "runs", "eval"):
            shutil.rmtree(out / sub, ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    table_path = out / "table.json"
    table: dict = json.loads(table_path.read_text()) if table_path.is_file() and not fresh else {}
    meta_path = out / "bench.json"
    meta: dict = json.loads(meta_path.read_text()) if meta_path.is_file() and not fresh else {}
    meta.update({"preset": bench.name, "config": to_dict(bench), "machine": machine_info(), "protocol": PROTOCOL,
                 "command": _command_line()})
    meta.setdefault("objects", {})
    ecfg = bench.eval_config()
    ecfg = dataclasses.replace(ecfg, progress=progress)
    # every train config is resolved once, up front: a config file edited while the benchmark runs
    # cannot give the variants (or the objects) different settings
    train_cfgs = {(o, v): variant_train_config(bench, o, v) for o in objects for v in bench.variants
                  if v in TRAINED_VARIANTS}
    for (o, v), c in train_cfgs.items():
        _check_no_test_selection(c, f"{o}/{v}")
    done: list[str] = []
    for obj in objects:
        t_obj = time.time()
        steps: dict = {}
        data = out / "data" / f"{obj}_{bench.world.preset}"
        runs = out / "runs" / obj
        steps["data"] = _dataset(bench, obj, data, log, progress)
        if not steps["data"]["reused"]:
            for stale in (runs, out / "eval" / obj):  # trained on (or scored from) other data
                shutil.rmtree(stale, ignore_errors=True)
        full_run = runs / "full"
        steps["full"] = _train_variant(train_cfgs[(obj, "full")], obj, "full", data, full_run, None, log, progress)
        for v in bench.variants:
            if v in TRAINED_VARIANTS and v != "full":
                steps[v] = _train_variant(train_cfgs[(obj, v)], obj, v, data, runs / v, full_run / "scene", log, progress)
        ctx = EvalContext.from_run(full_run, data)
        if "spring_mass" in bench.variants:
            steps["spring_mass"] = _fit_spring_mass(bench, obj, ctx, full_run, runs / "spring_mass", log, progress)
        models = {}
        for v in bench.variants:
            if v == "static":
                models[v] = StaticModel()
            elif v == "prior_only":  # full's kept weights, the network switched off
                models[v] = load_model(full_run / "checkpoint.pt", network=False)
            elif v == "spring_mass":
                models[v] = load_model(runs / "spring_mass" / SPRING_MASS_FILE)
            else:
                models[v] = load_model(runs / v / "checkpoint.pt")
        t_eval = time.time()
        table[obj] = {v: {} for v in bench.variants}
        union = {v: {} for v in bench.variants}  # depth over measured | rendered object (EXTRA_METRICS)
        n_eps = {}
        by_task: dict = {}  # {variant: {split: {task: {metric: mean over the task's episodes}}}}
        for split in SPLITS:
            log(f"[{obj}] evaluating {len(models)} variants on the {split} episodes")
            res = evaluate_models(models, ctx, split, {v: out / "eval" / obj / split / v for v in models}, ecfg,
                                  log=lambda s: log(f"[{obj}] {s}"))
            for v, r in res.items():
                table[obj][v][split] = {m: r["mean"].get(m) for m in METRICS}
                by_task.setdefault(v, {})[split] = task_means(r["episodes"])
                union[v][split] = {m: r["mean"].get(m) for m in EXTRA_METRICS}
                n_eps[split] = r["mean"]["episodes"]
        steps["eval"] = {"seconds": round(time.time() - t_eval, 1)}
        meta["objects"][obj] = {"steps": steps, "episodes": n_eps, "seconds": round(time.time() - t_obj, 1),
                                "finished": time.strftime("%Y-%m-%d %H:%M:%S"),
                                "train_configs": {v: c.to_dict() for (o, v), c in train_cfgs.items() if o == obj},
                                "data": str(data), "comparison_test": comparison(table, obj),
                                "per_task": by_task, "prior_test": prior_comparison(by_task),
                                "depth_union": union}
        log(f"[{obj}] done in {(time.time() - t_obj) / 60:.1f} min")
        meta["wall_seconds"] = round(time.time() - t_start, 1)
        meta["finished"] = time.strftime("%Y-%m-%d %H:%M:%S")
        done.append(obj)
        _write(out, table, meta, bench, own=done)
    return {"table": table, "meta": meta}


def _write(out: Path, table: dict, meta: dict, bench: BenchConfig, own: Optional[Sequence[str]] = None) -> None:
    """Write table.json / bench.json / table.md, merged with what other processes wrote there
    meanwhile: objects benchmarked in parallel (``--jobs``) into the same folder each add their own
    rows (an exclusive lock on ``OUT/.bench.lock`` around read-merge-write). For the objects this
    process benchmarked (``own``; default: all in ``table``) its rows win; for every other object the
    file's rows win (this process only holds what the file had when it started)."""
    own = set(table if own is None else own)
    with open(out / ".bench.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            for name, mine in (("table.json", table), ("bench.json", meta)):
                path = out / name
                if not path.is_file():
                    continue
                try:
                    theirs = json.loads(path.read_text())
                except json.JSONDecodeError:
                    continue
                if name == "table.json":
                    for obj, rows in theirs.items():
                        if obj not in own:
                            table[obj] = rows
                else:
                    for obj, info in theirs.get("objects", {}).items():
                        if obj not in own:
                            meta["objects"][obj] = info
                    meta["wall_seconds"] = max(float(meta.get("wall_seconds") or 0),
                                               float(theirs.get("wall_seconds") or 0))
            rank = {o: i for i, o in enumerate(OBJECTS)}
            table = {o: table[o] for o in sorted(table, key=lambda o: rank.get(o, len(rank)))}
            for name, text in (("table.json", json.dumps(_json_safe(table), indent=1)),
                               ("bench.json", json.dumps(_json_safe(meta), indent=1, default=str)),
                               ("table.md", table_markdown(table, bench, meta))):
                tmp = out / f".{name}.{os.getpid()}.tmp"
                tmp.write_text(text)
                os.replace(tmp, out / name)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
