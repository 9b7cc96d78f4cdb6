"""Photometric Gaussian-splat fit to calibrated views (3DGS-style, CPU-sized by default).

:func:`fit_splats` optimises the splats of a :class:`~soma_ros.core.splats.Splats` against the
object pixels of V views (:class:`soma_ros.scene.capture.CaptureViews`) with the public
:func:`soma_ros.core.render.render`:

* **Parameters**: means, log-scales, quaternions, opacity logits, SH DC colour and, from
  ``sh_start`` on, the degree-1 SH band (view-dependent colour, evaluated per camera before
  rasterising by :func:`soma_ros.core.splats.view_dependent_colors`). Degree 1 is used only
  when at least ``sh_min_views`` views are fitted: with fewer, a view-dependent colour can
  reproduce every training view exactly and still be wrong in between.
* **Loss per view** (over the object pixels, ignored pixels left out):
  ``(1 - lam) L1 + lam D-SSIM`` of the masked images (3DGS: lam = 0.2), plus
  ``alpha_weight`` x mean (alpha - mask)^2 over the view's crop (no splat where the mask
  says background, opaque inside), plus ``depth_weight`` x mean |rendered depth - depth| /
  median depth where the views carry depth (``CaptureViews.depth`` > 0 on object pixels).
* **Sparse-view safeguards**: ``scale_reg`` x mean(max scale) / spacing (no splat grows to
  cover what the few views do not constrain), ``aniso_reg`` x mean relu(log(max/min scale)
  - log ``max_aniso``) (no needles), ``opacity_reg`` x the mean binary entropy of the
  opacities (opacities go to 0 or 1, so that pruning removes the unsupported ones), the
  depth term, and early stopping on held-back pixels.
* **Densification** every ``densify_every`` iterations in [``densify_from``,
  ``densify_until``): a splat whose mean view-space gradient (NDC units, see below) is at
  least ``grad_threshold`` is cloned when its largest scale is below ``dense_scale`` x
  spacing, else split into two children sampled from it with scales / ``split_factor``.
  Growth is capped at ``max_splats`` (the splats with the largest gradients first).
* **Pruning** at the same steps and at the end: opacity below ``min_opacity``, or largest
  scale above ``max_scale`` x spacing, or (``hull_px`` >= 0) a centre that projects into a
  fitted view outside its object mask dilated by ``hull_px`` pixels (outside the visual
  hull); never below ``min_splats`` (the most opaque kept).
* **Opacity reset** every ``reset_every`` iterations before ``densify_until``: opacities
  clamped to at most ``reset_opacity`` (3DGS: 0.01), their optimiser state cleared.
* **Early stopping**: ``check_fraction`` of every view's object pixels, in ``check_block``
  square blocks, are left out of the loss; every ``check_every`` iterations their masked
  PSNR is measured, the best parameters are returned, and the fit stops after
  ``patience`` checks without improvement once densification is over.

``spacing`` is the median nearest-neighbour distance of the initial splat centres; every
size in the config is relative to it, so the config does not depend on the object's scale.

View-space gradient: the renderer's public API returns images, not its projected 2D means.
The gradient of the loss w.r.t. a splat's 2D mean is recovered from the gradient w.r.t. its
3D mean in the camera frame: u = fx x / z + cx depends on x only through u, so dL/du =
(dL/dx) z / fx (likewise v); in NDC units x W / 2 (resp. H / 2), as 3DGS thresholds it. (The
2D covariance also depends on x through the clamped projection Jacobian; that part is
neglected.) Views are rendered one at a time, so every view contributes its own norm.

Each view is rendered only over the bounding box of its object mask plus ``crop_margin``
pixels (a camera with shifted principal point): the loss looks at object pixels, so this
changes nothing but the cost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch

from soma_ros.core.cameras import Cameras
from soma_ros.core.geometry import covariance_from_scale_rot, quat_normalize, quat_to_rotmat
from soma_ros.core.metrics import masked_psnr, ssim_map
from soma_ros.core.render import render
from soma_ros.core.splats import Splats, sh_dc_to_rgb, view_dependent_colors

__all__ = ["FitConfig", "load_fit_config", "fit_splats", "densify_and_prune", "ParamState", "ViewCrop",
           "crop_views", "FIT_PRESETS"]

FIT_PRESETS = ("cpu", "quality")


@dataclass
class FitConfig:
    """Settings of :func:`fit_splats` (see the module docstring for every term).

    Sizes (``dense_scale``, ``max_scale``, ``init_scale``) are multiples of the initial
    splat spacing; ``lr_means`` is a fraction of the object's extent per step (decayed
    exponentially to ``lr_means_final`` of it at the last iteration).
    """

    iters: int = 1500
    lr_means: float = 2e-4
    lr_means_final: float = 0.01
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 5e-2
    lr_color: float = 2.5e-3
    lr_sh_rest: float = 1.25e-4
    sh_degree: int = 1
    sh_start: int = 500
    sh_min_views: int = 3
    sh_reg: float = 0.0
    lam: float = 0.2
    alpha_weight: float = 0.1
    depth_weight: float = 0.1
    scale_reg: float = 0.0
    aniso_reg: float = 0.0
    max_aniso: float = 10.0
    opacity_reg: float = 0.0
    init_scale: float = 0.0  # 0: keep the initial splats' scales
    densify_from: int = 100
    densify_until: int = 1000
    densify_every: int = 100
    grad_threshold: float = 2e-4
    dense_scale: float = 1.5
    split_factor: float = 1.6
    max_splats: int = 30000
    min_splats: int = 10
    min_opacity: float = 0.005
    max_scale: float = 20.0
    hull_px: int = -1  # >= 0: also prune splats whose centre falls outside a view's mask dilated by this many px
    reset_every: int = 0
    reset_opacity: float = 0.01
    views_per_iter: int = 1
    crop_margin: int = 16
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    check_fraction: float = 0.05
    check_block: int = 8
    check_every: int = 50
    patience: int = 4
    seed: int = 0
    log_every: int = 50
    history: list = field(default_factory=list)
    best: dict = field(default_factory=dict)

    def validate(self) -> "FitConfig":
        if self.iters < 0:
            raise ValueError(f"fit config: iters must be >= 0, got {self.iters}")
        for name in ("lr_means", "lr_scales", "lr_quats", "lr_opacity", "lr_color", "lr_sh_rest", "alpha_weight",
                     "depth_weight", "scale_reg", "aniso_reg", "opacity_reg", "sh_reg", "init_scale",
                     "grad_threshold", "min_opacity"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"fit config: {name} must be finite and >= 0, got {v}")
        if not 0 <= self.lam <= 1:
            raise ValueError(f"fit config: lam must lie in [0, 1], got {self.lam}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"fit config: sh_degree must be 0..3, got {self.sh_degree}")
        if not 0 < self.lr_means_final <= 1:
            raise ValueError(f"fit config: lr_means_final must lie in (0, 1], got {self.lr_means_final}")
        if not 1 <= self.min_splats <= self.max_splats:
            raise ValueError(f"fit config: need 1 <= min_splats <= max_splats, got {self.min_splats}, {self.max_splats}")
        if self.split_factor <= 1 or self.max_aniso < 1 or self.dense_scale <= 0 or self.max_scale <= 0:
            raise ValueError("fit config: split_factor > 1, max_aniso >= 1, dense_scale > 0 and max_scale > 0 needed")
        if not 0 <= self.check_fraction < 1:
            raise ValueError(f"fit config: check_fraction must lie in [0, 1), got {self.check_fraction}")
        if not 0 <= self.reset_opacity < 1:
            raise ValueError(f"fit config: reset_opacity must lie in [0, 1), got {self.reset_opacity}")
        for name in ("densify_every", "check_every", "check_block", "log_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"fit config: {name} must be >= 1, got {getattr(self, name)}")
        if self.views_per_iter < 0 or self.crop_margin < 0 or self.patience < 0 or self.reset_every < 0:
            raise ValueError("fit config: views_per_iter, crop_margin, patience and reset_every must be >= 0")
        return self


def load_fit_config(name_or_path: Union[str, Path], overrides: Optional[dict] = None) -> FitConfig:
    """A preset (``config/reconstruct/<name>.yaml``: cpu, quality) or a YAML path -> :class:`FitConfig`,
    unknown keys and bad types refused; ``overrides`` (a mapping) applied on top."""
    import yaml

    from soma_ros.core.config import ConfigError, from_dict, read_config
    from soma_ros.paths import resolve_config

    p = Path(name_or_path)
    if not (p.suffix in (".yaml", ".yml") and p.is_file()):
        try:
            p = resolve_config(f"reconstruct/{name_or_path}")
        except FileNotFoundError:
            raise FileNotFoundError(f"fit preset not found: {name_or_path} (presets: {', '.join(FIT_PRESETS)}, "
                                    "or a .yaml path)") from None
    data = read_config(p)  # with its base applied
    data = {**data, **(overrides or {})}
    for k in ("history", "best"):
        if k in data:
            raise ConfigError(f"{p}: {k}: not a setting")
    if "background" in data:
        data["background"] = tuple(data["background"])
    cfg = from_dict(FitConfig, data, where=f"{p.name}: ")
    try:
        return cfg.validate()
    except ValueError as exc:
        raise ConfigError(f"{p}: {exc}") from None


# ------------------------------------------------------------------ views, cropped
@dataclass
class ViewCrop:
    """One view cropped to its object: a 1-camera :class:`Cameras` of the crop size and the
    crop's pixels. ``fit``: object pixels the loss uses; ``check``: held-back object pixels;
    ``region``: pixels the alpha term looks at; ``depth``: metres, 0 = none."""

    index: int
    camera: Cameras
    gt: torch.Tensor  # [h, w, 3] measured colour x object mask
    mask: torch.Tensor  # [h, w] bool, object
    fit: torch.Tensor  # [h, w] bool
    check: torch.Tensor  # [h, w] bool
    region: torch.Tensor  # [h, w] bool
    depth: Optional[torch.Tensor]  # [h, w] or None
    full_size: tuple[int, int]  # (W, H) of the uncropped view


def crop_views(views, margin: int, check_fraction: float = 0.0, check_block: int = 8, seed: int = 0) -> list[ViewCrop]:
    """The views with a non-empty object mask, each cropped to its mask's bounding box + ``margin``."""
    V, H, W = views.masks.shape
    g = torch.Generator().manual_seed(seed)
    out = []
    for v in range(V):
        m = views.masks[v]
        if not m.any():
            continue
        ys, xs = torch.nonzero(m, as_tuple=True)
        y0, y1 = max(0, int(ys.min()) - margin), min(H, int(ys.max()) + 1 + margin)
        x0, x1 = max(0, int(xs.min()) - margin), min(W, int(xs.max()) + 1 + margin)
        K = views.cameras.K[v].clone()
        K[0, 2] -= x0
        K[1, 2] -= y0
        cam = Cameras(K=K[None], world_to_cam=views.cameras.world_to_cam[v:v + 1].clone(), width=x1 - x0,
                      height=y1 - y0, names=None if views.cameras.names is None else [views.cameras.names[v]])
        mc = m[y0:y1, x0:x1]
        region = torch.ones_like(mc)
        if views.ignore is not None:
            region &= ~views.ignore[v, y0:y1, x0:x1]
        hb, wb = -(-H // check_block), -(-W // check_block)
        pick = torch.rand(hb, wb, generator=g) < check_fraction
        full = pick.repeat_interleave(check_block, 0).repeat_interleave(check_block, 1)[:H, :W]
        check = full[y0:y1, x0:x1] & mc & region
        fit = mc & region & ~check
        depth = None
        if getattr(views, "depth", None) is not None:
            d = views.depth[v, y0:y1, x0:x1].float()
            if (d[fit] > 0).any():
                depth = d
        gt = views.images[v, y0:y1, x0:x1] * mc[..., None]
        out.append(ViewCrop(v, cam, gt, mc, fit, check, region & ~check, depth, (W, H)))
    if not out:
        raise ValueError("fit_splats: every view's object mask is empty")
    return out


# ------------------------------------------------------------------ parameters + optimiser
_NAMES = ("means", "log_scales", "quats", "logit_op", "sh_dc", "sh_rest")


class ParamState:
    """The optimised splat parameters and their Adam state; rows can be cloned, split, removed."""

    def __init__(self, splats: Splats, cfg: FitConfig, sh_bands: int, extent: float, spacing: float):
        op = splats.opacities.detach().float().clamp(1e-4, 1 - 1e-4)
        rest = splats.sh_rest.detach().float()
        if rest.shape[1] < sh_bands:
            rest = torch.cat([rest, rest.new_zeros(len(splats), sh_bands - rest.shape[1], 3)], dim=1)
        scales = splats.scales.detach().float()
        if cfg.init_scale > 0:
            scales = torch.full_like(scales, cfg.init_scale * spacing)
        self.p = {
            "means": splats.means.detach().float().clone(),
            "log_scales": scales.clamp_min(1e-7).log(),
            "quats": splats.quats.detach().float().clone(),
            "logit_op": torch.log(op / (1 - op)),
            "sh_dc": splats.sh_dc.detach().float().clone(),
            "sh_rest": rest[:, :sh_bands].clone(),
        }
        self.lr = {"means": cfg.lr_means * extent, "log_scales": cfg.lr_scales, "quats": cfg.lr_quats,
                   "logit_op": cfg.lr_opacity, "sh_dc": cfg.lr_color, "sh_rest": cfg.lr_sh_rest}
        self.mass_total = float(splats.mass.sum()) if splats.mass is not None else 1.0
        self._build()

    def _build(self, state: Optional[dict] = None) -> None:
        for k in _NAMES:
            self.p[k] = self.p[k].detach().requires_grad_(True)
        groups = [{"params": [self.p[k]], "lr": self.lr[k], "name": k} for k in _NAMES]
        self.opt = torch.optim.Adam(groups, eps=1e-15)
        if state:
            for k in _NAMES:
                if k in state:
                    self.opt.state[self.p[k]] = state[k]

    def __len__(self) -> int:
        return int(self.p["means"].shape[0])

    def set_lr(self, name: str, lr: float) -> None:
        for g in self.opt.param_groups:
            if g["name"] == name:
                g["lr"] = lr

    def remap(self, src: torch.Tensor, new_values: dict[str, torch.Tensor], fresh: torch.Tensor) -> None:
        """Rows become ``new_values`` (every name, [M, ...]); row i inherits the optimiser state of
        old row ``src[i]`` unless ``fresh[i]`` (zero state)."""
        state = {}
        for k in _NAMES:
            st = self.opt.state.get(self.p[k])
            if st:
                ns = {"step": st["step"]}
                for s in ("exp_avg", "exp_avg_sq"):
                    t = st[s][src].clone()
                    t[fresh] = 0
                    ns[s] = t
                state[k] = ns
            self.p[k] = new_values[k].detach().clone()
        self._build(state)

    def reset_opacity(self, value: float) -> None:
        with torch.no_grad():
            lo = math.log(value / (1 - value)) if value > 0 else -10.0
            self.p["logit_op"].clamp_(max=lo)
        st = self.opt.state.get(self.p["logit_op"])
        if st:
            st["exp_avg"].zero_()
            st["exp_avg_sq"].zero_()

    def snapshot(self) -> dict[str, torch.Tensor]:
        return {k: v.detach().clone() for k, v in self.p.items()}

    def splats(self, values: Optional[dict] = None) -> Splats:
        """The current (or ``values``') parameters as Splats, the total mass spread evenly."""
        p = values if values is not None else {k: v.detach() for k, v in self.p.items()}
        q = p["quats"] / p["quats"].norm(dim=-1, keepdim=True).clamp_min(1e-12)
        n = p["means"].shape[0]
        mass = p["means"].new_full((n,), self.mass_total / max(n, 1))
        return Splats(means=p["means"].clone(), quats=q.clone(), scales=p["log_scales"].exp(),
                      opacities=torch.sigmoid(p["logit_op"]), sh_dc=p["sh_dc"].clone(), sh_rest=p["sh_rest"].clone(),
                      mass=mass)


@torch.no_grad()
def densify_and_prune(state: ParamState, grad_mean: torch.Tensor, cfg: FitConfig, spacing: float,
                      generator: Optional[torch.Generator] = None, grow: bool = True, hull=None) -> dict:
    """One densify (clone / split by mean view-space gradient ``grad_mean`` [N]) and prune step
    on ``state`` (see the module docstring); returns counts. The result has between
    ``min(N, cfg.min_splats)`` and ``max(N, cfg.max_splats)`` splats. ``hull``: a callable
    means [M, 3] -> bool [M], True for a centre outside the visual hull (pruned)."""
    p = {k: v.detach() for k, v in state.p.items()}
    n = len(state)
    if grad_mean.shape != (n,):
        raise ValueError(f"densify_and_prune: grad_mean must be [{n}], got {list(grad_mean.shape)}")
    smax = p["log_scales"].exp().max(-1).values
    n_clone = n_split = 0
    src = torch.arange(n)
    fresh = torch.zeros(n, dtype=torch.bool)
    new = dict(p)
    if grow:
        cand = torch.nonzero(grad_mean >= cfg.grad_threshold, as_tuple=True)[0]
        room = max(0, cfg.max_splats - n)  # a clone or a split adds one splat
        if len(cand) > room:
            cand = cand[torch.argsort(grad_mean[cand], descending=True)[:room]]
        big = smax[cand] > cfg.dense_scale * spacing
        clone, split = cand[~big], cand[big]
        n_clone, n_split = len(clone), len(split)
        parts_src = [torch.arange(n), clone, split]
        means = [p["means"], p["means"][clone]]
        log_s = [p["log_scales"], p["log_scales"][clone]]
        if len(split):
            R = quat_to_rotmat(quat_normalize(p["quats"][split]))
            s = p["log_scales"][split].exp()
            offs = torch.randn(2, len(split), 3, generator=generator) * s[None]
            child = p["means"][split][None] + torch.einsum("kij,nkj->nki", R, offs)  # [2, S, 3]
            means[0] = means[0].clone()
            means[0][split] = child[0]
            means.append(child[1])
            ls = p["log_scales"][split] - math.log(cfg.split_factor)
            log_s[0] = log_s[0].clone()
            log_s[0][split] = ls
            log_s.append(ls)
        else:
            means.append(p["means"][:0])
            log_s.append(p["log_scales"][:0])
        src = torch.cat(parts_src)
        fresh = torch.zeros(len(src), dtype=torch.bool)
        fresh[n:] = True
        if len(split):
            fresh[split] = True
        new = {k: p[k][src] for k in _NAMES}
        new["means"] = torch.cat(means)
        new["log_scales"] = torch.cat(log_s)
    # prune
    op = torch.sigmoid(new["logit_op"])
    smax_new = new["log_scales"].exp().max(-1).values
    drop = (op < cfg.min_opacity) | (smax_new > cfg.max_scale * spacing)
    if hull is not None:
        drop |= hull(new["means"])
    keep_min = min(len(src), cfg.min_splats)
    if int((~drop).sum()) < keep_min:
        order = torch.argsort(op, descending=True)[:keep_min]
        drop = torch.ones_like(drop)
        drop[order] = False
    keep = ~drop
    n_pruned = int(drop.sum())
    state.remap(src[keep], {k: v[keep] for k, v in new.items()}, fresh[keep])
    seen = grad_mean[grad_mean > 0]
    q = [float(x) for x in torch.quantile(seen, torch.tensor([0.5, 0.9]))] if len(seen) else [0.0, 0.0]
    return {"clone": n_clone, "split": n_split, "pruned": n_pruned, "splats": len(state), "grad_p50": q[0],
            "grad_p90": q[1]}


def outside_hull(views, dilate_px: int):
    """A callable means [M, 3] -> bool [M]: True where a centre projects inside some view's image
    but outside its object mask dilated by ``dilate_px`` (ignored pixels count as inside)."""
    k = 2 * dilate_px + 1
    masks = torch.nn.functional.max_pool2d(views.masks[:, None].float(), k, stride=1, padding=dilate_px)[:, 0] > 0
    if views.ignore is not None:
        masks |= views.ignore
    V, H, W = masks.shape

    def test(means: torch.Tensor) -> torch.Tensor:
        uv, z = views.cameras.project(means.detach().to(views.cameras.K.dtype))
        out = torch.zeros(means.shape[0], dtype=torch.bool)
        for v in range(V):
            u_i, v_i = uv[v, :, 0].floor().long(), uv[v, :, 1].floor().long()
            ok = (z[v] > 0.01) & (u_i >= 0) & (u_i < W) & (v_i >= 0) & (v_i < H)
            hit = torch.zeros_like(ok)
            hit[ok] = masks[v][v_i[ok], u_i[ok]]
            out |= ok & ~hit
        return out

    return test


# ------------------------------------------------------------------ the fit
def _spacing(means: torch.Tensor) -> float:
    from scipy.spatial import cKDTree

    x = means.detach().double().numpy()
    if len(x) < 2:
        return 1e-3
    d = cKDTree(x).query(x, k=2)[0][:, 1]
    return float(max(np.median(d), 1e-6))


def _view_loss(state: ParamState, vc: ViewCrop, cfg: FitConfig, degree: int, bg: torch.Tensor,
               depth_scale: float) -> tuple[torch.Tensor, dict]:
    p = state.p
    colors = view_dependent_colors(p["means"], p["sh_dc"], p["sh_rest"], vc.camera.centers(), degree) \
        if degree > 0 else sh_dc_to_rgb(p["sh_dc"])
    covs = covariance_from_scale_rot(p["log_scales"].exp(), quat_normalize(p["quats"]))
    out = render(p["means"], covs, colors, torch.sigmoid(p["logit_op"]), vc.camera, background=bg)
    pred = out.rgb[0]
    fm = vc.fit.float()
    nf = fm.sum().clamp_min(1.0)
    l1 = ((pred - vc.gt).abs().sum(-1) * fm).sum() / (3 * nf)
    mask3 = vc.mask[..., None].float()
    smap = ssim_map((pred * mask3)[None], (vc.gt)[None], 11, 1.5, padding="same")[0]
    dssim = 1.0 - (smap * fm).sum() / nf
    loss = (1 - cfg.lam) * l1 + cfg.lam * dssim
    terms = {"l1": float(l1.detach()), "dssim": float(dssim.detach())}
    if cfg.alpha_weight > 0:
        rg = vc.region.float()
        a = ((out.alpha[0] - vc.mask.float()) ** 2 * rg).sum() / rg.sum().clamp_min(1.0)
        loss = loss + cfg.alpha_weight * a
        terms["alpha"] = float(a.detach())
    if cfg.depth_weight > 0 and vc.depth is not None:
        dm = (vc.fit & (vc.depth > 0)).float()
        dl = ((out.depth[0] - vc.depth).abs() * dm).sum() / dm.sum().clamp_min(1.0) / depth_scale
        loss = loss + cfg.depth_weight * dl
        terms["depth"] = float(dl.detach())
    return loss, terms


def _check_psnr(state: ParamState, crops: list[ViewCrop], degree: int, bg: torch.Tensor) -> float:
    vals = []
    with torch.no_grad():
        sp = state.splats()
        for vc in crops:
            if not vc.check.any():
                continue
            col = sp.colors_seen_from(vc.camera.centers(), degree)
            out = render(sp.means, sp.covariances(), col, sp.opacities, vc.camera, background=bg)
            vals.append(float(masked_psnr(out.rgb[0], vc.gt, vc.check)))
    return float(np.mean(vals)) if vals else float("nan")


def fit_splats(init: Splats, views, cfg: FitConfig, progress: bool = True) -> Splats:
    """Fit ``init`` to ``views`` (:class:`soma_ros.scene.capture.CaptureViews`) photometrically; returns
    the fitted splats (count changed by densification / pruning, total mass kept, SH bands
    ``sh_rest`` [N, 3, 3] when degree 1 was fitted). ``cfg.history`` receives the loss, the
    splat count and the check PSNR over the iterations; ``cfg.best`` the early-stop choice."""
    from tqdm import tqdm

    cfg.validate()
    if len(init) == 0:
        raise ValueError("fit_splats: no initial splats")
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    crops = crop_views(views, cfg.crop_margin, cfg.check_fraction, cfg.check_block, cfg.seed)
    n_views = len({vc.index for vc in crops})
    degree = cfg.sh_degree if n_views >= cfg.sh_min_views else 0
    bands = (degree + 1) ** 2 - 1
    pts = init.means.detach().float()
    extent = float((pts.max(0).values - pts.min(0).values).norm())
    spacing = _spacing(pts)
    state = ParamState(init, cfg, bands, max(extent, 1e-3), spacing)
    bg = torch.tensor(cfg.background, dtype=torch.float32)
    dvals = [vc.depth[vc.depth > 0] for vc in crops if vc.depth is not None]
    depth_scale = float(torch.cat(dvals).median()) if dvals else 1.0
    grow = cfg.densify_until > cfg.densify_from and cfg.max_splats > len(init)
    hull = outside_hull(views, cfg.hull_px) if cfg.hull_px >= 0 else None
    cfg.history.clear()
    cfg.best = {"iter": -1, "psnr_check": float("nan"), "sh_degree": degree, "spacing_m": spacing,
                "extent_m": extent}
    has_check = any(vc.check.any() for vc in crops)
    best_state = None
    if has_check:
        cfg.best["psnr_check"] = _check_psnr(state, crops, 0, bg)
        best_state = (state.snapshot(), 0)
    stale = 0
    gsum = torch.zeros(len(state))
    gcnt = torch.zeros(len(state))
    order = torch.randperm(len(crops), generator=gen).tolist()
    per = len(crops) if cfg.views_per_iter <= 0 else min(cfg.views_per_iter, len(crops))
    lr0 = state.lr["means"]
    bar = tqdm(range(cfg.iters), desc="fit splats", disable=not progress, unit="it")
    k = 0
    for it in bar:
        if cfg.iters > 1 and lr0 > 0:
            state.set_lr("means", lr0 * cfg.lr_means_final ** (it / (cfg.iters - 1)))
        d_now = degree if it >= cfg.sh_start else 0
        state.opt.zero_grad(set_to_none=True)
        total = 0.0
        terms = {}
        for _ in range(per):
            if k >= len(order):
                order, k = torch.randperm(len(crops), generator=gen).tolist(), 0
            vc = crops[order[k]]
            k += 1
            prev = None if state.p["means"].grad is None else state.p["means"].grad.clone()
            loss, terms = _view_loss(state, vc, cfg, d_now, bg, depth_scale)
            reg = _regularisers(state, cfg, spacing)
            (loss + reg / per).backward()
            total += float(loss.detach())
            if grow and it < cfg.densify_until:
                g = state.p["means"].grad if prev is None else state.p["means"].grad - prev
                with torch.no_grad():
                    R = vc.camera.world_to_cam[0, :3, :3]
                    t = vc.camera.world_to_cam[0, :3, 3]
                    gc = g @ R.T
                    z = (state.p["means"].detach() @ R.T + t)[:, 2]
                    W, H = vc.full_size
                    gu = gc[:, 0] * z / vc.camera.K[0, 0, 0] * (W / 2)
                    gv = gc[:, 1] * z / vc.camera.K[0, 1, 1] * (H / 2)
                    norm = torch.sqrt(gu * gu + gv * gv)
                    seen = g.abs().sum(-1) > 0
                    gsum += torch.where(seen, norm, torch.zeros_like(norm))
                    gcnt += seen.float()
        if d_now == 0 and state.p["sh_rest"].grad is not None:
            state.p["sh_rest"].grad = None
        state.opt.step()
        with torch.no_grad():
            state.p["log_scales"].clamp_(max=math.log(cfg.max_scale * spacing * 2))
        step = it + 1
        if cfg.densify_from <= step < cfg.densify_until and step % cfg.densify_every == 0:
            info = densify_and_prune(state, gsum / gcnt.clamp_min(1), cfg, spacing, gen, grow=grow, hull=hull)
            cfg.history.append({"iter": step, **info})
            gsum, gcnt = torch.zeros(len(state)), torch.zeros(len(state))
        if cfg.reset_every and step < cfg.densify_until and step % cfg.reset_every == 0:
            state.reset_opacity(cfg.reset_opacity)
            cfg.history.append({"iter": step, "opacity_reset": cfg.reset_opacity})
        if it % cfg.log_every == 0 or it == cfg.iters - 1:
            cfg.history.append({"iter": it, "loss": total / per, "splats": len(state), **terms})
            bar.set_postfix(loss=f"{total / per:.4f}", n=len(state))
        if has_check and (step % cfg.check_every == 0 or it == cfg.iters - 1):
            ps = _check_psnr(state, crops, d_now, bg)
            cfg.history.append({"iter": step, "psnr_check": ps, "splats": len(state)})
            if ps > cfg.best["psnr_check"]:
                cfg.best.update({"iter": step, "psnr_check": ps})
                best_state = (state.snapshot(), d_now)
                stale = 0
            elif step >= cfg.densify_until:
                stale += 1
                if cfg.patience and stale >= cfg.patience:
                    cfg.best["stopped_at"] = step
                    break
    final = state.splats(best_state[0] if best_state is not None else None)
    used = best_state[1] if best_state is not None else (degree if cfg.iters > cfg.sh_start else 0)
    if used == 0:
        final = Splats(final.means, final.quats, final.scales, final.opacities, final.sh_dc, None, final.mass)
    # the last prune: splats that ended transparent or oversized
    keep = (final.opacities >= cfg.min_opacity) & (final.scales.max(-1).values <= cfg.max_scale * spacing)
    if hull is not None:
        keep &= ~hull(final.means)
    if int(keep.sum()) >= min(len(final), cfg.min_splats):
        final = final.index(keep)
        final.mass = final.mass.new_full((len(final),), state.mass_total / max(len(final), 1))
    cfg.best["num_splats"] = len(final)
    cfg.best["sh_degree_used"] = used
    return final


def _regularisers(state: ParamState, cfg: FitConfig, spacing: float) -> torch.Tensor:
    p = state.p
    reg = p["means"].new_zeros(())
    if cfg.scale_reg > 0 or cfg.aniso_reg > 0:
        ls = p["log_scales"]
        if cfg.scale_reg > 0:
            reg = reg + cfg.scale_reg * (ls.max(-1).values.exp() / spacing).mean()
        if cfg.aniso_reg > 0:
            ratio = ls.max(-1).values - ls.min(-1).values
            reg = reg + cfg.aniso_reg * torch.relu(ratio - math.log(cfg.max_aniso)).mean()
    if cfg.opacity_reg > 0:
        o = torch.sigmoid(p["logit_op"]).clamp(1e-6, 1 - 1e-6)
        reg = reg + cfg.opacity_reg * (-(o * o.log() + (1 - o) * (1 - o).log())).mean()
    if cfg.sh_reg > 0 and p["sh_rest"].shape[1] > 0:
        reg = reg + cfg.sh_reg * (p["sh_rest"] ** 2).mean()
    return reg
