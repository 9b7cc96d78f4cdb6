"""`soma eval`: open-loop rollouts of a model on a dataset split, scored against the recordings.

For every episode of the split, every model starts from the same initial
state -- G_0 of the run's scene aligned to the episode's first frame
(:class:`soma_ros.training.train.EpisodeStore`, exactly what training and validation
use) -- and is rolled out at the frame rate under the episode's recorded joint
states (the robot actions in the sim frame), with no feedback from the
recording. Each predicted frame is rendered in every recorded camera and
scored (:mod:`soma_ros.core.scoring` documents the protocol: masked PSNR /
SSIM / LPIPS, table-completed depth AbsRel / RMSE, Chamfer against the
evaluation-only ground-truth object points).

Outputs in OUT (one model)::

    metrics.json     {"variant", "split", "dataset", "model", "mean": {metric: value},
                      "episodes": {name: {metric: value, "per_camera", "frames", ...}},
                      "protocol", "seconds", "rollout_ms_per_frame"}
    table.md         per-episode rows and the mean
    sheets/<episode>.png   contact sheets: measured | simulated | |error| per camera
    videos/<episode>.mp4   (with video=True) every scored frame

:func:`evaluate_models` scores several models in one pass over the episodes
(each episode is read and aligned once); the accuracy benchmark uses it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch

from soma_ros.core.render import render
from soma_ros.core.robot import RobotModel

from soma_ros.evaluation.baselines import RolloutModel
from soma_ros.training.config import TrainConfig, load_train_config
from soma_ros.data.dataset import EpisodeRef, load_dataset
from soma_ros.data.sources import usable_episodes
from soma_ros.evaluation.ground_truth import GroundTruthError, read_ground_truth_points
from soma_ros.core.scoring import (
    LOWER_IS_BETTER,
    METRICS,
    EvalMetricsConfig,
    aggregate_episodes,
    aggregate_frames,
    score_frame,
    table_depth,
)
from soma_ros.evaluation.viz import EpisodeSheet, EpisodeVideo, sample_frames
from soma_ros.scene.files import load_scene
from soma_ros.training.train import EpisodeStore

__all__ = [
    "EvalConfig",
    "EvalContext",
    "evaluate_models",
    "write_model_report",
    "metrics_table_md",
    "METRIC_LABELS",
    "format_metric",
    "PROTOCOL",
]

METRIC_LABELS = {
    "abs_rel": "Abs Rel ↓", "rmse": "RMSE (m) ↓", "psnr": "PSNR ↑", "ssim": "SSIM ↑", "lpips": "LPIPS ↓",
    "chamfer": "Chamfer (m) ↓",
}

PROTOCOL = {
    "frames": "frames 1..T-1 of every episode (frame 0 is the shared initial state), open loop at the frame rate",
    "initial_state": "G_0 of the run's scene aligned to the episode's frame-0 object points (same for every model)",
    "images": "rendered over black vs GT x object mask, both x (1 - robot mask), whole image; PSNR, SSIM "
              "(11x11 Gaussian), LPIPS (AlexNet); +inf PSNR (both black) left out",
    "depth": "paper rule: masked-out pixels take the table-plane depth; prediction rendered over the table "
             "(D + (1 - alpha) table); scored on the measured object's valid pixels & ~robot (the same pixels "
             "for every model); metres. abs_rel_union / rmse_union in metrics.json: scored on (GT object | "
             "rendered alpha > 0.5) & ~robot",
    "chamfer": "all simulated splat means vs the ground-truth object points (/world/object_points, evaluation "
               "only), 0.5 (mean a->b + mean b->a) nearest-neighbour distance, metres",
    "aggregation": "per episode: mean over scored frames and cameras; per split: mean over episodes",
}


def format_metric(metric: str, value: Optional[float]) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if metric == "psnr":
        return f"{value:.2f}"
    if metric in ("chamfer", "rmse"):
        return f"{value:.4f}"
    return f"{value:.3f}"


@dataclass
class EvalConfig:
    """What to score and what to draw."""

    metrics: EvalMetricsConfig = field(default_factory=EvalMetricsConfig)
    frame_stride: int = 1  # score every k-th frame (the rollout always runs at the frame rate)
    max_episodes: Optional[int] = None
    contact_sheets: bool = True
    sheet_frames: int = 5
    tile_width: int = 200
    video: bool = False
    video_fps: float = 10.0
    error_max: float = 0.5
    progress: bool = True
    device: str = "cpu"  # rollouts, rendering and metrics: cpu | cuda | auto (cuda when available)

    def validate(self) -> "EvalConfig":
        self.metrics.validate()
        if self.device not in ("cpu", "cuda", "auto"):
            raise ValueError(f"EvalConfig.device must be cpu, cuda or auto, got {self.device!r}")
        if self.frame_stride < 1 or self.sheet_frames < 1 or self.tile_width < 16:
            raise ValueError("EvalConfig: frame_stride >= 1, sheet_frames >= 1, tile_width >= 16 required")
        if self.max_episodes is not None and self.max_episodes < 1:
            raise ValueError("EvalConfig.max_episodes must be >= 1")
        if not (self.video_fps > 0 and self.error_max > 0):
            raise ValueError("EvalConfig: video_fps and error_max must be > 0")
        return self


class EvalContext:
    """What every evaluated model shares: the dataset, the scene (G_0, hierarchy, table, gravity),
    the data / scene-alignment config of the run, and the per-episode initial splats."""

    def __init__(self, data_dir: str | Path, train_cfg: TrainConfig, scene_dir: str | Path,
                 cache_dir: Optional[str | Path] = None, strict: Optional[bool] = None) -> None:
        # a dataset folder or bag, or several bags (soma_ros.data.sources)
        self.data_dir = [Path(p) for p in data_dir] if isinstance(data_dir, (list, tuple)) else Path(data_dir)
        self.scene_dir = Path(scene_dir)
        # keep at most two prepared episodes in memory (a paper-preset episode is ~1.6 GB of images)
        self.cfg = dataclasses.replace(train_cfg, data=dataclasses.replace(train_cfg.data, cache_episodes=2))
        self.bundle, self.hierarchy = load_scene(self.scene_dir)
        dc = self.cfg.data
        robot = RobotModel.from_config(self.cfg.robot, dtype=torch.float64)
        self.skipped: list[str] = []
        self.refs = usable_episodes(load_dataset(self.data_dir, test_fraction=dc.split_test_fraction, seed=dc.split_seed),
                                    robot, dc, self.skipped.append, strict)
        self.store = EpisodeStore(self.refs, robot, self.cfg, self.bundle, self.hierarchy,
                                  None if cache_dir is None else Path(cache_dir))
        # score the cameras each bag has (another rig's set), posed from its own TF
        self.store.rig_cameras = False
        self.scene = self.bundle.scene_context()

    @staticmethod
    def from_run(run_dir: str | Path, data_dir: str | Path, scene_dir: Optional[str | Path] = None,
                 strict: Optional[bool] = None) -> "EvalContext":
        """Context of a training run folder (``train_config.yaml``, ``scene/``, ``cache/``)."""
        run = Path(run_dir)
        cfg_path = run / "train_config.yaml"
        if not cfg_path.is_file():
            raise FileNotFoundError(f"{run}: no train_config.yaml (is it a `soma train` run folder?)")
        cfg = load_train_config(cfg_path)
        scene = Path(scene_dir) if scene_dir is not None else run / "scene"
        if not (scene / "scene.json").is_file():
            raise FileNotFoundError(f"scene bundle not found: {scene}")
        # the run's cache of aligned initial states is keyed by episode name only: use it only for
        # the dataset and scene the run was trained on
        cache = None
        ck = run / "checkpoint.pt"
        if scene_dir is None and ck.is_file():
            from soma_ros.core.checkpoint import read_checkpoint

            trained_on = read_checkpoint(ck)["extra"].get("dataset")
            if trained_on and not isinstance(data_dir, (list, tuple)) and Path(trained_on).resolve() == Path(data_dir).resolve():
                cache = run / "cache"
        return EvalContext(data_dir, cfg, scene, cache, strict)

    def episodes(self, split: str, max_episodes: Optional[int] = None) -> list[EpisodeRef]:
        refs = [r for r in self.refs if r.in_split(split)]
        if not refs:
            splits = sorted({r.split for r in self.refs})
            raise ValueError(f"{self.data_dir}: no '{split}' episodes (splits: {', '.join(splits)})")
        return refs[:max_episodes] if max_episodes else refs


def _ground_truth(ref: EpisodeRef, stamps_ns: torch.Tensor, sim_frame: str) -> tuple[Optional[torch.Tensor], str]:
    if sim_frame != "world":
        return None, f"sim frame '{sim_frame}' is not the ground truth's 'world'"
    try:
        pts = read_ground_truth_points(ref.bag, stamps_ns=[int(s) for s in stamps_ns.tolist()])
    except GroundTruthError as exc:
        return None, str(exc)
    return torch.from_numpy(pts), ""


def evaluate_models(
    models: dict[str, RolloutModel],
    ctx: EvalContext,
    split: str,
    out_dirs: dict[str, Path],
    cfg: Optional[EvalConfig] = None,
    log: Callable[[str], None] = print,
) -> dict[str, dict]:
    """Score every model on every episode of ``split``; write each model's report into
    ``out_dirs[name]``; returns {name: metrics dict (as metrics.json)}."""
    from soma_ros.core.lpips import load_lpips

    cfg = (cfg or EvalConfig()).validate()
    if set(models) != set(out_dirs):
        raise ValueError("evaluate_models: give one output folder per model")
    refs = ctx.episodes(split, cfg.max_episodes)
    dev = torch.device("cuda" if cfg.device == "cuda" or (cfg.device == "auto" and torch.cuda.is_available()) else "cpu")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("eval device 'cuda' but torch sees no CUDA device")
    for model in models.values():
        model.to(dev)
    lp = load_lpips(device=dev) if cfg.metrics.with_lpips else None
    t_start = time.time()
    per_model: dict[str, dict] = {n: {"episodes": {}, "rollout_seconds": 0.0, "rollout_frames": 0,
                                     "notes": list(ctx.skipped)}
                                  for n in models}
    bar = None
    total_frames = sum(int(r.frames or 0) for r in refs) * len(models)
    if cfg.progress:
        from tqdm import tqdm

        bar = tqdm(total=total_frames or None, desc=f"soma eval {split}", unit="frame", dynamic_ncols=True)
    for ref in refs:
        ep = ctx.store.episode(ref.name)
        init = ctx.store.initial_splats(ref.name)
        colors, opac = init.colors().float().to(dev), init.opacities.float().to(dev)
        gt_pts, note = _ground_truth(ref, ep.stamps_ns, ctx.bundle.sim_frame)
        if gt_pts is not None and gt_pts.shape[0] != ep.num_frames:
            raise ValueError(f"{ref.name}: {gt_pts.shape[0]} ground-truth frames for {ep.num_frames} episode frames")
        first = 1 if cfg.metrics.skip_first else 0
        scored = [t for t in range(first, ep.num_frames) if (t - first) % cfg.frame_stride == 0]
        scored_set = set(scored)
        if not scored:
            raise ValueError(f"{ref.name}: no frame to score ({ep.num_frames} frames)")
        for name, model in models.items():
            rec = per_model[name]
            if note and note not in rec["notes"]:
                rec["notes"].append(f"{ref.name}: Chamfer not scored: {note}")
            out = Path(out_dirs[name])
            sheet = EpisodeSheet(f"{name} | {ref.name} ({ref.task or ''}, {split})  measured | simulated | |error|",
                                 sample_frames(scored, cfg.sheet_frames), cfg.tile_width, cfg.error_max) \
                if cfg.contact_sheets else None
            video = EpisodeVideo(out / "videos" / f"{ref.name}.mp4", cfg.video_fps, cfg.tile_width, cfg.error_max) \
                if cfg.video else None
            frames = []
            stream = iter(model.rollout(ep, init, ctx.scene))
            for t in range(ep.num_frames):
                t_roll = time.perf_counter()
                try:
                    means, covs = next(stream)
                except StopIteration:
                    raise RuntimeError(f"{name}: rollout of {ref.name} stopped at frame {t} of {ep.num_frames}") from None
                rec["rollout_seconds"] += time.perf_counter() - t_roll
                if bar is not None:
                    bar.update(1)
                if t not in scored_set:
                    continue
                means, covs = means.detach().float().to(dev), covs.detach().float().to(dev)
                if means.shape != (len(init), 3) or covs.shape != (len(init), 3, 3):
                    raise ValueError(f"{name}: frame {t} has means {list(means.shape)}, covs {list(covs.shape)}")
                cams = ep.cameras(t, device=dev)
                with torch.no_grad():
                    r = render(means, covs, colors, opac, cams)
                table = table_depth(cams, ctx.scene.plane_normal, float(ctx.scene.plane_offset))
                fs = score_frame(t, r.rgb, r.depth, r.alpha, ep.rgb[t].to(dev), ep.depth[t].to(dev),
                                 ep.object_mask[t].to(dev), ep.robot_mask[t].to(dev), table, ep.camera_names, means,
                                 None if gt_pts is None else gt_pts[t].to(dev), cfg.metrics, lp)
                frames.append(fs)
                if sheet is not None and sheet.wants(t):
                    sheet.add(t, ep.camera_names, ep.rgb[t], ep.object_mask[t], ep.robot_mask[t], r.rgb.cpu(),
                              f"{_mean(fs.camera_values('psnr')):.1f}dB")
                if video is not None:
                    video.add(t, ep.camera_names, ep.rgb[t], ep.object_mask[t], ep.robot_mask[t], r.rgb.cpu())
            rec["rollout_frames"] += ep.num_frames
            if len(frames) != len(scored):
                raise RuntimeError(f"{name}: rollout of {ref.name} gave {len(frames)} scored frames, expected {len(scored)}")
            summary = aggregate_frames(frames)
            summary["task"] = ref.task
            summary["per_frame"] = {
                "frame": [f.frame for f in frames],
                **{m: [_mean([v for v in f.camera_values(m)]) for f in frames] for m in METRICS if m != "chamfer"},
                "chamfer": [f.chamfer for f in frames],
            }
            rec["episodes"][ref.name] = summary
            if sheet is not None:
                sheet.write(out / "sheets" / f"{ref.name}.png")
            if video is not None:
                video.close()
    if bar is not None:
        bar.close()
    results = {}
    for name, model in models.items():
        rec = per_model[name]
        res = {
            "variant": name,
            "split": split,
            "dataset": str(ctx.data_dir) if isinstance(ctx.data_dir, Path) else ";".join(map(str, ctx.data_dir)),
            "scene": str(ctx.scene_dir),
            "model": model.describe(),
            "mean": aggregate_episodes(rec["episodes"]),
            "episodes": rec["episodes"],
            "protocol": PROTOCOL,
            "notes": rec["notes"],
            "rollout_ms_per_frame": 1000.0 * rec["rollout_seconds"] / max(rec["rollout_frames"], 1),
            "seconds": round(time.time() - t_start, 1),
        }
        write_model_report(Path(out_dirs[name]), res)
        results[name] = res
        log(f"{name} [{split}]: " + ", ".join(f"{m}={format_metric(m, res['mean'].get(m))}" for m in METRICS))
    return results


def _mean(vals: Sequence[float]) -> float:
    fin = [v for v in vals if math.isfinite(v)]
    return sum(fin) / len(fin) if fin else math.nan


def metrics_table_md(res: dict) -> str:
    """Markdown table of one model's metrics.json: one row per episode and the mean."""
    head = "| episode | task | frames | " + " | ".join(METRIC_LABELS[m] for m in METRICS) + " |"
    sep = "|" + "---|" * (3 + len(METRICS))
    rows = [head, sep]
    for name, e in res["episodes"].items():
        rows.append(f"| {name} | {e.get('task') or ''} | {e['frames']} | "
                    + " | ".join(format_metric(m, e.get(m)) for m in METRICS) + " |")
    mean = res["mean"]
    rows.append(f"| **mean ({mean['episodes']} episodes)** | | | "
                + " | ".join(f"**{format_metric(m, mean.get(m))}**" for m in METRICS) + " |")
    title = f"# {res['variant']} on {res['split']} episodes of {res['dataset']}\n\n"
    foot = "\n\nProtocol: " + "; ".join(f"{k}: {v}" for k, v in res["protocol"].items()) + "\n"
    if res.get("notes"):
        foot += "\nNotes: " + "; ".join(res["notes"]) + "\n"
    return title + "\n".join(rows) + foot


def _json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def write_model_report(out: Path, res: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / ".metrics.json.tmp"
    tmp.write_text(json.dumps(_json_safe(res), indent=1))
    os.replace(tmp, out / "metrics.json")
    (out / "table.md").write_text(metrics_table_md(res))


def better(metric: str, a: float, b: float) -> bool:
    """True if value a is better than b for this metric."""
    return a < b if LOWER_IS_BETTER[metric] else a > b
