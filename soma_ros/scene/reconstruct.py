"""Scene set-up: initial splats G_0 from a capture folder or an episode bag."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from soma_ros.scene.capture import FitConfig, fit_splats, initial_splats_from_capture, read_capture


def _save_rgb(path: Path, rgb01: np.ndarray) -> None:
    import cv2

    cv2.imwrite(str(path), (np.clip(rgb01, 0, 1) * 255).round().astype(np.uint8)[..., ::-1])


def reconstruct_capture(folder: Path, out: Path, holdout: Optional[int] = None, iters: int = 300,
                        scale: float = 0.5, progress: bool = True) -> dict:
    """Fit splats on every view but `holdout`; render the held-out view and score it.

    Writes OUT/splats.ply, OUT/metrics.json (psnr_holdout: masked PSNR of the
    held-out view at full resolution), OUT/holdout_render.png,
    OUT/holdout_compare.png (measured | rendered | |error|).
    """
    from soma_ros.core.metrics import masked_psnr
    from soma_ros.core.ply import write_ply
    from soma_ros.core.render import render_splats

    t0 = time.time()
    views = read_capture(folder)
    V = views.num_views
    if holdout is not None and not 0 <= holdout < V:
        raise ValueError(f"--holdout-view {holdout} is out of range: the capture has {V} views")
    train_idx = [i for i in range(V) if i != holdout]
    init = initial_splats_from_capture(views, train_idx)
    cfg = FitConfig(iters=iters)  # defaults tuned for novel views (see FitConfig)
    fit_views = views.select(train_idx).resized(scale)
    bg = torch.zeros(3)
    fitted = fit_splats(init, fit_views, cfg, progress=progress)
    write_ply(out / "splats.ply", fitted)
    metrics: dict = {"capture": str(folder), "views": V, "train_views": train_idx, "holdout_view": holdout,
                     "num_splats": len(fitted), "iters": iters, "fit_resolution_scale": scale,
                     "fit_config": {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("history", "best")},
                     "loss_history": cfg.history}
    if holdout is not None:
        hv = views.select([holdout])
        with torch.no_grad():
            ren = render_splats(fitted, hv.cameras, background=bg)
            ren0 = render_splats(init, hv.cameras, background=bg)
        gt = hv.images[0]
        m = hv.masks[0]
        metrics["psnr_holdout"] = float(masked_psnr(ren.rgb[0], gt, m))
        metrics["psnr_holdout_init"] = float(masked_psnr(ren0.rgb[0], gt, m))
        train_psnr = []
        for i in train_idx:
            tv = views.select([i])
            with torch.no_grad():
                r = render_splats(fitted, tv.cameras, background=bg)
            train_psnr.append(float(masked_psnr(r.rgb[0], tv.images[0], tv.masks[0])))
        metrics["psnr_train_views"] = train_psnr
        gt_masked = (gt * m[..., None]).numpy()
        rr = ren.rgb[0].numpy()
        err = np.abs(rr * m[..., None].numpy() - gt_masked).mean(-1, keepdims=True).repeat(3, -1) * 4
        _save_rgb(out / "holdout_render.png", rr)
        _save_rgb(out / "holdout_compare.png", np.concatenate([gt_masked, rr * m[..., None].numpy(), err], axis=1))
    metrics["seconds"] = round(time.time() - t0, 1)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return {k: v for k, v in metrics.items() if k != "loss_history"}


def reconstruct_bag(bag: Path, out: Path, robot: str = "panda", object_name: str = "rope", iters: Optional[int] = None,
                    progress: bool = True, config: Optional[str] = None, ply: Optional[Path] = None) -> dict:
    """Scene set-up from an episode bag (see :mod:`soma_ros.scene.scene_setup`): G_0 from the fused masked
    depth of the first frame(s) refined photometrically (or a user ``ply`` already in the sim frame),
    table plane and gravity, robot -> sim transform, hierarchy. Writes the scene bundle into OUT
    (splats.ply, scene.json, hierarchy.pt, setup.json), OUT/metrics.json (masked PSNR of G_0 in every
    camera of the first set-up frame, before and after the refinement) and OUT/frame0_compare.png
    (recorded object | render, one row per camera)."""
    from soma_ros.core.config import load_model_config, load_object_config
    from soma_ros.core.metrics import masked_psnr
    from soma_ros.core.ply import load_splats
    from soma_ros.core.render import render_splats
    from soma_ros.core.robot import RobotModel

    from soma_ros.training.config import TrainConfig, load_train_config
    from soma_ros.data.dataset import prepare_episode
    from soma_ros.scene.scene_setup import setup_scene, splats_from_points
    from soma_ros.scene.files import save_scene

    t0 = time.time()
    cfg = load_train_config(config) if config else TrainConfig().validate()
    if iters is not None:
        cfg.scene.photometric_iters = int(iters)
    rm = RobotModel.from_config(robot, dtype=torch.float64)
    obj = load_object_config(object_name)
    mc = load_model_config(cfg.model, object=obj)
    ep = prepare_episode(Path(bag), rm, cfg.data)
    user = load_splats(ply) if ply is not None else None
    setup = setup_scene(ep, cfg.scene, obj.name, robot, obj.total_mass, mc.hierarchy.thresholds,
                        mc.hierarchy.seed_fraction, init_splats=user, progress=progress)
    out = Path(out)
    save_scene(out, setup.bundle, setup.hierarchy, setup.info)
    t = [f for f in cfg.scene.frames if f < ep.num_frames][0]
    cams = ep.cameras(t)
    pts, cols = ep.object_points([t], cfg.scene.erode_px)
    raw, _ = splats_from_points(pts, cols, cfg.scene.num_splats, obj.total_mass, cfg.scene.splat_scale_factor,
                                cfg.scene.opacity)
    with torch.no_grad():
        ren = render_splats(setup.bundle.splats, cams)
        ren0 = render_splats(raw, cams)
    per_cam = {}
    rows = []
    for c, name in enumerate(ep.camera_names):
        m = ep.loss_mask[t, c]
        if m.any():
            per_cam[name] = {"psnr_masked": float(masked_psnr(ren.rgb[c], ep.rgb[t, c], m)),
                             "psnr_masked_unrefined": float(masked_psnr(ren0.rgb[c], ep.rgb[t, c], m)),
                             "object_pixels": int(m.sum())}
        gt = (ep.rgb[t, c] * m[..., None]).numpy()
        rows.append(np.concatenate([gt, ren.rgb[c].numpy()], axis=1))
    _save_rgb(out / "frame0_compare.png", np.concatenate(rows, axis=0))
    info = {"bag": str(bag), "out": str(out), "num_splats": len(setup.bundle.splats),
            "hierarchy_sizes": setup.hierarchy.sizes, "frame": t, "cameras": per_cam,
            "gravity": setup.bundle.gravity.tolist(), "table_normal": setup.bundle.table_normal.tolist(),
            "table_offset": setup.bundle.table_offset, "base_to_sim": setup.bundle.base_to_sim,
            "user_ply": None if ply is None else str(ply), "seconds": round(time.time() - t0, 1)}
    (out / "metrics.json").write_text(json.dumps(info, indent=2))
    return info
