"""Pictures and figures of a reconstruction: per-view metrics, contact sheet, splat count plot."""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from soma_ros.core.splats import Splats

__all__ = ["render_views", "view_metrics", "contact_sheet", "plot_fit_history", "save_rgb"]


def save_rgb(path: Path, rgb01: np.ndarray) -> None:
    import cv2

    cv2.imwrite(str(path), (np.clip(rgb01, 0, 1) * 255).round().astype(np.uint8)[..., ::-1])


def render_views(splats: Splats, views, with_alpha: bool = False):
    """[V, H, W, 3] renders of ``splats`` in every view (view-dependent colour when it has SH
    bands); with ``with_alpha`` also their [V, H, W] accumulated opacity."""
    from soma_ros.core.render import render

    out, alpha = [], []
    with torch.no_grad():
        cov = splats.covariances()
        for v in range(views.num_views):
            cam = views.cameras.select([v])
            col = splats.colors_seen_from(cam.centers().to(splats.means.dtype))
            r = render(splats.means, cov, col, splats.opacities, cam)
            out.append(r.rgb[0])
            alpha.append(r.alpha[0].reshape(r.rgb.shape[1:3]))
    return (torch.stack(out), torch.stack(alpha)) if with_alpha else torch.stack(out)


def view_metrics(renders: torch.Tensor, views, names: Optional[Sequence[str]] = None, roles: Optional[dict] = None,
                 with_lpips: bool = True, alphas: Optional[torch.Tensor] = None) -> list[dict]:
    """Per view: masked PSNR (object pixels), SSIM averaged over the object pixels, and the
    evaluation protocol's full-image PSNR / SSIM / LPIPS of (render, measured x mask), see
    :func:`soma_ros.core.metrics.image_metrics`. With ``alphas`` ([V, H, W]) also
    ``alpha_iou``: the rendered silhouette (alpha > 0.5) against the mask, intersection over
    union, which shows whether the splats sit where the view sees the object, and
    ``alpha_inside``: the mean rendered alpha over the mask (whether the object is covered at all)."""
    from soma_ros.core.metrics import image_metrics, ssim

    rows = []
    for v in range(views.num_views):
        m = views.masks[v]
        ign = None if views.ignore is None else views.ignore[v]
        r = image_metrics(renders[v], views.images[v], m, ign, with_lpips=with_lpips)
        om = m if ign is None else (m & ~ign)
        gt = views.images[v] * om[..., None]
        r["ssim_masked"] = float(ssim(renders[v] * om[..., None], gt, mask=om, padding="same"))
        r["view"] = v if names is None else names[v]
        if roles is not None:
            r["role"] = roles.get(v, "")
        r["object_pixels"] = int(om.sum())
        if alphas is not None:
            sil = alphas[v] > 0.5
            union = int((sil | m).sum())
            r["alpha_iou"] = float((sil & m).sum()) / union if union else 1.0
            r["alpha_inside"] = float(alphas[v][m].mean()) if bool(m.any()) else float("nan")
        rows.append(r)
    return rows


def contact_sheet(path: Path, renders: torch.Tensor, views, crop: bool = True, margin: int = 24) -> None:
    """One row per view: measured x mask | rendered | |error| x 4 (object pixels), cropped to the
    union of the objects' bounding boxes (+ ``margin``) when ``crop``."""
    m = views.masks
    gt = (views.images * m[..., None]).numpy()
    rr = renders.numpy()
    err = np.abs(rr * m[..., None].numpy() - gt).mean(-1, keepdims=True).repeat(3, -1) * 4
    y0, y1, x0, x1 = 0, m.shape[1], 0, m.shape[2]
    if crop and m.any():
        ys, xs = torch.nonzero(m.any(0), as_tuple=True)
        y0, y1 = max(0, int(ys.min()) - margin), min(m.shape[1], int(ys.max()) + 1 + margin)
        x0, x1 = max(0, int(xs.min()) - margin), min(m.shape[2], int(xs.max()) + 1 + margin)
    rows = [np.concatenate([gt[v, y0:y1, x0:x1], rr[v, y0:y1, x0:x1], err[v, y0:y1, x0:x1]], axis=1)
            for v in range(len(rr))]
    save_rgb(path, np.concatenate(rows, axis=0))


def plot_fit_history(path: Path, history: list, title: str = "photometric fit") -> None:
    """PNG: splat count and check-pixel PSNR over the iterations of a fit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cnt = sorted({(h["iter"], h["splats"]) for h in history if "splats" in h})
    chk = sorted({(h["iter"], h["psnr_check"]) for h in history if "psnr_check" in h})
    fig, ax = plt.subplots(figsize=(6, 3.2), dpi=120)
    if cnt:
        ax.plot([c[0] for c in cnt], [c[1] for c in cnt], color="tab:blue", label="splats")
    ax.set_xlabel("iteration")
    ax.set_ylabel("splats", color="tab:blue")
    for h in history:
        if "opacity_reset" in h:
            ax.axvline(h["iter"], color="0.7", lw=0.8, ls=":")
    if chk:
        ax2 = ax.twinx()
        ax2.plot([c[0] for c in chk], [c[1] for c in chk], color="tab:red", label="held-back pixels PSNR")
        ax2.set_ylabel("check-pixel PSNR (dB)", color="tab:red")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
