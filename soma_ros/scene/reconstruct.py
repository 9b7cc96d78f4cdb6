"""Scene set-up: initial splats G_0 from a capture folder or an episode bag."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from soma_ros.scene.capture import fit_splats, initial_splats_from_capture, read_capture


def _save_rgb(path: Path, rgb01: np.ndarray) -> None:
    from soma_ros.scene.recon_report import save_rgb

    save_rgb(path, rgb01)


def reconstruct_capture(folder: Path, out: Path, holdout: Optional[int] = None, iters: Optional[int] = None,
                        scale: float = 1.0, progress: bool = True, preset: str = "cpu",
                        overrides: Optional[dict] = None) -> dict:
    """Fit splats on every view but `holdout` (:func:`soma_ros.scene.splat_fit.fit_splats`, settings from
    ``preset``: cpu, quality or a YAML path; ``iters`` and ``overrides`` on top) and score every view.

    Initial splats: the capture's object points (or the visual hull of the training masks);
    depth supervision: the capture's depth images where it has them, else its object points
    projected into the training views. Writes into OUT: splats.ply; metrics.json (per view:
    masked PSNR, object-pixel SSIM, protocol PSNR / SSIM / LPIPS, its role; ``psnr_holdout``,
    ``psnr_train_views``; fit settings, history, wall and CPU seconds); contact_sheet.png
    (measured | rendered | |error| x 4, one row per view, held-out last); fit_history.png
    (splat count and check-pixel PSNR over the fit); holdout_render.png and
    holdout_compare.png with a held-out view.
    """
    from soma_ros.core.ply import write_ply

    from soma_ros.scene.recon_report import contact_sheet, plot_fit_history, render_views, view_metrics
    from soma_ros.scene.splat_fit import load_fit_config

    t0, c0 = time.time(), time.process_time()
    views = read_capture(folder)
    V = views.num_views
    if holdout is not None and not 0 <= holdout < V:
        raise ValueError(f"--holdout-view {holdout} is out of range: the capture has {V} views")
    train_idx = [i for i in range(V) if i != holdout]
    cfg = load_fit_config(preset, overrides)
    if iters is not None:
        cfg.iters = int(iters)
    init = initial_splats_from_capture(views, train_idx)
    fit_views = views.select(train_idx)
    depth_source = "capture depth" if fit_views.depth is not None else None
    if fit_views.depth is None and views.points is not None:
        fit_views = fit_views.with_point_depth()
        depth_source = "capture points projected into the training views"
    fit_views = fit_views.resized(scale)
    fitted = fit_splats(init, fit_views, cfg, progress=progress)
    cpu_fit = time.process_time() - c0
    wall_fit = time.time() - t0
    write_ply(out / "splats.ply", fitted)
    order = train_idx + ([holdout] if holdout is not None else [])
    ov = views.select(order)
    roles = {k: ("held-out" if i == holdout else "train") for k, i in enumerate(order)}
    ren, alpha = render_views(fitted, ov, with_alpha=True)
    rows = view_metrics(ren, ov, names=[f"view_{i}" for i in order], roles=roles, alphas=alpha)
    ren0 = render_views(init, ov)
    for r, r0 in zip(rows, view_metrics(ren0, ov, with_lpips=False)):
        r["psnr_masked_init"] = r0["psnr_masked"]
    contact_sheet(out / "contact_sheet.png", ren, ov)
    plot_fit_history(out / "fit_history.png", cfg.history, title=f"{Path(folder).name}: splats over the fit")
    metrics: dict = {"capture": str(folder), "views": V, "train_views": train_idx, "holdout_view": holdout,
                     "num_splats_init": len(init), "num_splats": len(fitted), "preset": str(preset),
                     "iters": cfg.iters, "fit_resolution_scale": scale, "depth_supervision": depth_source,
                     "early_stop": cfg.best, "per_view": rows,
                     "psnr_train_views": [r["psnr_masked"] for r in rows if r["role"] == "train"],
                     "seconds_fit": round(wall_fit, 1), "cpu_seconds_fit": round(cpu_fit, 1),
                     "fit_config": {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("history", "best")},
                     "fit_history": cfg.history}
    if holdout is not None:
        h = rows[-1]
        metrics["psnr_holdout"] = h["psnr_masked"]
        metrics["psnr_holdout_init"] = h["psnr_masked_init"]
        m = ov.masks[-1]
        gt_masked = (ov.images[-1] * m[..., None]).numpy()
        rr = ren[-1].numpy()
        err = np.abs(rr * m[..., None].numpy() - gt_masked).mean(-1, keepdims=True).repeat(3, -1) * 4
        _save_rgb(out / "holdout_render.png", rr)
        _save_rgb(out / "holdout_compare.png", np.concatenate([gt_masked, rr * m[..., None].numpy(), err], axis=1))
    metrics["seconds"] = round(time.time() - t0, 1)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return {k: v for k, v in metrics.items() if k not in ("fit_history", "fit_config")}


def reconstruct_bag(bag: Path, out: Path, robot: str = "panda", object_name: str = "rope", iters: Optional[int] = None,
                    progress: bool = True, config=None, ply: Optional[Path] = None) -> dict:
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

    from soma_ros.data.dataset import prepare_episode
    from soma_ros.scene.scene_setup import setup_scene, splats_from_points
    from soma_ros.scene.files import save_scene

    t0 = time.time()
    if config is None:
        raise ValueError("reconstruct_bag needs the training config whose data and scene sections it follows")
    cfg = config
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
