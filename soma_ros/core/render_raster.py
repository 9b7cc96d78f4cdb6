"""Vectorised pure-torch tile rasterizer for projected 2D Gaussians (CPU and GPU).

This is the compositing half of :func:`soma_ros.core.render.render`; the
projection half (3D -> 2D, EWA) lives in ``render.py``. Everything here works
on *visible* splats, i.e. (camera, splat) pairs that survived culling, V in
total, already projected to pixels.

Pipeline
--------
1. :func:`build_plan` (no grad): each visible splat has a pixel-space
   bounding box of the ellipse on which its contribution is cut off; the
   tiles under that box are enumerated with tensor ops (``repeat_interleave``,
   no Python loop over splats), for splats whose box covers >= 9 tiles the
   tiles that the ellipse provably misses are dropped (exact minimum of the
   quadratic form over the tile rectangle), and the (tile, splat)
   intersections are stably sorted by tile id after being generated in depth
   order, so every tile list runs front to back. Non-empty
   tiles are ordered by list length and grouped into chunks of similar length
   so the per-chunk padding to ``L = max list length`` wastes little work and
   each chunk touches at most ``max_chunk_elems`` (pixel, splat) pairs.
2. :class:`_CompositeFn` (autograd Function): forward composites every chunk
   front to back (cumulative product of 1 - alpha along the depth-sorted
   list) and accumulates ``K`` feature channels with one batched matmul;
   backward recomputes each chunk (nothing of size pixels x splats is kept
   between forward and backward) and evaluates the analytic gradient.

Per-pixel rule (identical in forward, backward and the brute-force reference
in the tests): with ``d = pixel_centre - mean2d``, ``power = 0.5 d^T conic d``
and ``s = log(opacity) - power``, a splat contributes to a pixel iff
``s > s_min = max(log(alpha_min), log(opacity) - 0.5 * sigma_cutoff**2)``
(i.e. alpha before clamping >= alpha_min and the pixel is inside the
``sigma_cutoff``-sigma ellipse), with ``alpha = min(alpha_max, exp(s))``.
Front-to-back, splat i is used iff the transmittance *after* it is still
> ``transmittance_min`` (gsplat's rule: the splat that would take T below the
threshold and all later ones are skipped). Output channel k of a pixel is
``sum_i alpha_i T_i feat_ik`` with ``T_i = prod_{j<i} (1 - alpha_j)``.

Because splats are binned by their exact cut-off ellipse, the result does
not depend on the tile size.

CPU performance notes (torch 2.13, one thread): boolean masks / ``where`` are
5-20x slower than arithmetic, and ``exp`` of arguments below about -87 takes
a scalar slow path (30-100x); the hot loop therefore uses ``threshold`` and
clamps instead of masks. ``cumprod`` along L is the most expensive op left.
Chunks of ~2**17 (pixel, splat) pairs were fastest (cache-sized temporaries;
no large allocations, so no glibc page-fault trap).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass
class Projected:
    """Visible (camera, splat) pairs after projection and culling; V entries."""

    cam_idx: torch.Tensor  # [V] long
    splat_idx: torch.Tensor  # [V] long
    mean2d: torch.Tensor  # [V, 2] pixels
    conic: torch.Tensor  # [V, 3] inverse of cov2d: (a, b, c) = [[a, b], [b, c]]
    cov2d: torch.Tensor  # [V, 3] (sxx, sxy, syy) including eps2d
    depth: torch.Tensor  # [V] camera-frame z of the mean
    opacity: torch.Tensor  # [V]
    smin: torch.Tensor  # [V] cut-off on s = log(opacity) - power
    pmax: torch.Tensor  # [V] cut-off on power


__all__ = ["Projected", "RasterPlan", "build_plan", "composite"]


@dataclass
class _Chunk:
    tiles: torch.Tensor  # [B] long, global tile ids (cam * TY * TX + ty * TX + tx)
    gidx: torch.Tensor  # [B, L] long, indices into the V visible splats (0 where padded)
    valid: torch.Tensor  # [B, L] bool, False on padding


@dataclass
class RasterPlan:
    """Sorted tile lists for one render; built by :func:`build_plan`, no gradients."""

    n_cams: int
    width: int
    height: int
    tile: int
    tiles_x: int
    tiles_y: int
    chunks: list  # list[_Chunk]
    n_isect: int  # number of (tile, splat) intersections after culling
    n_pairs: int  # number of (pixel, splat) pairs evaluated (incl. padding)


def _bbox_tiles(mean2d: torch.Tensor, half: torch.Tensor, width: int, height: int, tile: int):
    """Tile ranges [V] (inclusive) of the pixel centres within mean2d +- half; and a keep mask."""
    # pixel (col, row) has its centre at (col + 0.5, row + 0.5)
    col_min = torch.ceil(mean2d[:, 0] - half[:, 0] - 0.5)
    col_max = torch.floor(mean2d[:, 0] + half[:, 0] - 0.5)
    row_min = torch.ceil(mean2d[:, 1] - half[:, 1] - 0.5)
    row_max = torch.floor(mean2d[:, 1] + half[:, 1] - 0.5)
    keep = (col_max >= 0) & (row_max >= 0) & (col_min <= width - 1) & (row_min <= height - 1)
    keep &= (col_min <= col_max) & (row_min <= row_max)
    col_min = col_min.clamp(0, width - 1).long()
    col_max = col_max.clamp(0, width - 1).long()
    row_min = row_min.clamp(0, height - 1).long()
    row_max = row_max.clamp(0, height - 1).long()
    return col_min // tile, col_max // tile, row_min // tile, row_max // tile, keep


def _min_quadform_on_rect(dx0, dx1, dy0, dy1, a, b, c):
    """Minimum of q(x, y) = 0.5 (a x^2 + 2 b x y + c y^2) over [dx0, dx1] x [dy0, dy1].

    All inputs are [M]; (a, b, c) is positive definite. Returns [M].
    """
    inside = (dx0 <= 0) & (dx1 >= 0) & (dy0 <= 0) & (dy1 >= 0)

    def q(x, y):
        return 0.5 * (a * x * x + 2.0 * b * x * y + c * y * y)

    best = None
    for xe in (dx0, dx1):  # vertical edges: x fixed, y* = -b x / c clamped
        y = torch.minimum(torch.maximum(-b * xe / c, dy0), dy1)
        v = q(xe, y)
        best = v if best is None else torch.minimum(best, v)
    for ye in (dy0, dy1):  # horizontal edges
        x = torch.minimum(torch.maximum(-b * ye / a, dx0), dx1)
        best = torch.minimum(best, q(x, ye))
    return torch.where(inside, torch.zeros_like(best), best)


def _stable_argsort_ids(ids: torch.Tensor, n_ids: int) -> torch.Tensor:
    """Stable argsort of small non-negative integer ids [M] (long result).

    On CPU with < 2**16 distinct ids numpy's radix sort of uint16 is ~5x faster
    than torch.sort; otherwise torch's stable sort of int32.
    """
    if ids.device.type == "cpu" and n_ids <= 1 << 16:
        import numpy as np

        return torch.from_numpy(np.argsort(ids.numpy().astype(np.uint16), kind="stable")).long()
    return torch.sort(ids.to(torch.int32), stable=True).indices


@torch.no_grad()
def build_plan(
    mean2d: torch.Tensor,
    conic: torch.Tensor,
    cov2d_diag: torch.Tensor,
    pmax: torch.Tensor,
    depth: torch.Tensor,
    cam_idx: torch.Tensor,
    n_cams: int,
    width: int,
    height: int,
    tile: int,
    max_chunk_elems: int,
    tile_cull: bool = True,
) -> RasterPlan:
    """Bin V visible splats into tiles and plan the compositing chunks.

    Args:
        mean2d: [V, 2] pixel coordinates of the projected means.
        conic: [V, 3] inverse 2D covariance (a, b, c) = [[a, b], [b, c]].
        cov2d_diag: [V, 2] diagonal of the 2D covariance (sigma_x^2, sigma_y^2).
        pmax: [V] largest ``power`` at which the splat still contributes.
        depth: [V] camera-frame z used for sorting (front to back).
        cam_idx: [V] long camera index of each visible splat.
    """
    V = mean2d.shape[0]
    for name, t, shape in (
        ("mean2d", mean2d, (V, 2)),
        ("conic", conic, (V, 3)),
        ("cov2d_diag", cov2d_diag, (V, 2)),
        ("pmax", pmax, (V,)),
        ("depth", depth, (V,)),
        ("cam_idx", cam_idx, (V,)),
    ):
        if tuple(t.shape) != shape:
            raise ValueError(f"build_plan: {name} must be {list(shape)}, got {list(t.shape)}")
    dev = mean2d.device
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    n_tiles = n_cams * tiles_x * tiles_y
    P = tile * tile
    empty = RasterPlan(n_cams, width, height, tile, tiles_x, tiles_y, [], 0, 0)
    if V == 0:
        return empty

    # exact axis-aligned half extents of the ellipse {power <= pmax}, + rounding margin
    half = torch.sqrt(2.0 * pmax[:, None] * cov2d_diag) * (1.0 + 1e-5) + 1e-4
    tx0, tx1, ty0, ty1, keep = _bbox_tiles(mean2d, half, width, height, tile)

    # Intersections are generated splat by splat in depth order; a *stable* sort
    # by tile id then leaves every tile list sorted front to back.
    order = torch.argsort(depth, stable=True)
    order = order[keep[order]]
    Vs = int(order.numel())
    if Vs == 0:
        return empty
    tx0, tx1, ty0, ty1 = tx0[order], tx1[order], ty0[order], ty1[order]
    nx = (tx1 - tx0 + 1).to(torch.int32)
    ny = (ty1 - ty0 + 1).to(torch.int32)
    n_per = nx * ny
    M = int(n_per.sum())
    base_id = (cam_idx[order] * (tiles_x * tiles_y) + ty0 * tiles_x + tx0).to(torch.int32)
    start = torch.cumsum(n_per, 0, dtype=torch.int32) - n_per
    ints = torch.stack([base_id, nx, start], dim=1)
    r = torch.repeat_interleave(ints, n_per.long(), dim=0, output_size=M)  # [M, 3] int32
    k = torch.arange(M, device=dev, dtype=torch.int32) - r[:, 2]
    qy = torch.div(k, r[:, 1], rounding_mode="floor")
    qx = k - qy * r[:, 1]
    tile_id = r[:, 0] + qy * tiles_x + qx  # [M] int32
    rank = torch.repeat_interleave(torch.arange(Vs, device=dev, dtype=torch.int32), n_per.long(),
                                   output_size=M)
    if tile_cull:
        # drop bbox tiles that the cut-off ellipse does not reach (corners); only for
        # splats with >= 9 bbox tiles and >= 2 in each direction, for smaller ones the
        # test costs more than the few empty tiles it removes
        big_r = torch.repeat_interleave((nx > 1) & (ny > 1) & (n_per >= 9), n_per.long(), output_size=M)
        rows = torch.nonzero(big_r, as_tuple=False)[:, 0]
        if rows.numel() > 0:
            vb = order[rank[rows].long()]
            tx = (tx0[rank[rows].long()] + qx[rows]).to(mean2d.dtype)
            ty = (ty0[rank[rows].long()] + qy[rows]).to(mean2d.dtype)
            x0 = tx * tile + 0.5
            x1 = torch.clamp((tx + 1) * tile, max=width) - 0.5
            y0 = ty * tile + 0.5
            y1 = torch.clamp((ty + 1) * tile, max=height) - 0.5
            m = mean2d[vb]
            cn = conic[vb]
            qmin = _min_quadform_on_rect(
                x0 - m[:, 0], x1 - m[:, 0], y0 - m[:, 1], y1 - m[:, 1], cn[:, 0], cn[:, 1], cn[:, 2]
            )
            miss = qmin > pmax[vb] * (1.0 + 1e-5) + 1e-5
            keep_r = torch.ones(M, dtype=torch.bool, device=dev)
            keep_r[rows[miss]] = False
            tile_id, rank = tile_id[keep_r], rank[keep_r]
    M = int(tile_id.numel())
    if M == 0:
        return empty
    perm = _stable_argsort_ids(tile_id, n_tiles)
    tile_sorted = tile_id[perm].long()
    gid_sorted = order[rank[perm].long()]  # visible-splat index, per tile front to back

    counts = torch.bincount(tile_sorted, minlength=n_tiles)
    offsets = torch.cumsum(counts, 0) - counts
    nonempty = torch.nonzero(counts, as_tuple=False)[:, 0]
    cnt_ne = counts[nonempty]
    cnt_sorted, o2 = torch.sort(cnt_ne, descending=True, stable=True)
    tiles_sorted = nonempty[o2]
    cnt_list = cnt_sorted.tolist()

    chunks = []
    n_pairs = 0
    i = 0
    n_ne = len(cnt_list)
    while i < n_ne:
        L = int(cnt_list[i])
        B = max(1, min(n_ne - i, max_chunk_elems // (P * L)))
        tb = tiles_sorted[i : i + B]
        ar = torch.arange(L, device=dev)
        cnt_b = cnt_sorted[i : i + B]
        valid = ar[None, :] < cnt_b[:, None]
        pos = offsets[tb][:, None] + ar[None, :]
        pos = torch.where(valid, pos, torch.zeros_like(pos))
        gidx = torch.where(valid, gid_sorted[pos], torch.zeros_like(pos))
        chunks.append(_Chunk(tiles=tb, gidx=gidx, valid=valid))
        n_pairs += B * L * P
        i += B
    return RasterPlan(n_cams, width, height, tile, tiles_x, tiles_y, chunks, M, n_pairs)


def _tile_local_coords(tile: int, dtype, device):
    """Pixel-centre offsets from the tile centre: (lx [T], ly [T]), in pixels."""
    off = torch.arange(tile, dtype=dtype, device=device) + 0.5 - 0.5 * tile
    return off, off


def _tile_centres(tiles: torch.Tensor, plan: RasterPlan, dtype):
    """Centres (cx [B], cy [B]) in pixels of the global tile ids ``tiles`` [B]."""
    per_cam = plan.tiles_x * plan.tiles_y
    local = tiles % per_cam
    ty = local // plan.tiles_x
    tx = local % plan.tiles_x
    half = 0.5 * plan.tile
    return tx.to(dtype) * plan.tile + half, ty.to(dtype) * plan.tile + half


_BIG = 1e20  # turns a signed difference into a 0/1 step with clamp (no bool masks: faster on CPU)


def _chunk_alpha(ch: _Chunk, packed: torch.Tensor, plan: RasterPlan, alpha_max: float):
    """alpha of every (pixel, splat) pair of a chunk, [B, Ti, Tj, L].

    packed: [V, 7] = (mx, my, a, b, c, log_opacity, s_min). With
    ``s = log(opacity) - power``, ``alpha = min(exp(s), alpha_max)`` where
    ``s > s_min`` and 0 elsewhere (and on padding). The cut-off is evaluated as
    ``threshold(s - s_min, 0, -inf)`` then ``exp(s - s_min) * exp(s_min)``: no
    boolean masks, which are slow on CPU (see the comment on exp below). Also returns the per-(tile, splat)
    quantities mlx, mly, a, b, c [B, L] (means relative to the tile centre).
    """
    T = plan.tile
    B, L = ch.gidx.shape
    prm = packed[ch.gidx.reshape(-1)].reshape(B, L, -1)
    cx, cy = _tile_centres(ch.tiles, plan, packed.dtype)
    mlx = prm[..., 0] - cx[:, None]  # [B, L]
    mly = prm[..., 1] - cy[:, None]
    a, b, c = prm[..., 2], prm[..., 3], prm[..., 4]
    smin = prm[..., 6]
    rel0 = (prm[..., 5] - smin).masked_fill(~ch.valid, -math.inf)  # log o - s_min
    esmin = torch.exp(smin).masked_fill(~ch.valid, 0.0)
    lx, ly = _tile_local_coords(T, packed.dtype, packed.device)
    dx = lx[None, :, None] - mlx[:, None, :]  # [B, Tj, L]
    dy = ly[None, :, None] - mly[:, None, :]  # [B, Ti, L]
    # s - s_min = (log o - s_min) - 0.5 (a dx^2 + 2 b dx dy + c dy^2): separable parts on [B, T, L]
    sx = rel0[:, None, :] - 0.5 * a[:, None, :] * dx * dx  # [B, Tj, L]
    sy = -0.5 * c[:, None, :] * dy * dy  # [B, Ti, L]
    nbdx = -b[:, None, :] * dx  # [B, Tj, L]
    rel = torch.addcmul(sx[:, None, :, :], nbdx[:, None, :, :], dy[:, :, None, :])  # [B,Ti,Tj,L]
    rel += sy[:, :, None, :]
    # outside the cut-off: -80 rather than -inf (exp of arguments below ~-87 takes a
    # scalar slow path on CPU, 30-100x slower), then exact zeros via a second threshold
    F.threshold_(rel, 0.0, -80.0)
    alpha = rel.exp_().mul_(esmin[:, None, None, :]).clamp_(max=alpha_max)
    F.threshold_(alpha, 1e-30, 0.0)  # in-cut-off alphas are >= alpha_min > 1e-30
    return alpha, dict(mlx=mlx, mly=mly, a=a, b=b, c=c)


def _blend_weights(alpha: torch.Tensor, t_min: float, need_all: bool):
    """Front-to-back weights w = alpha * T_excl * keep along the last dim (L)."""
    one_m = torch.rsub(alpha, 1.0)
    t_incl = torch.cumprod(one_m, dim=-1)
    t_excl = t_incl / one_m
    w = alpha * t_excl
    # transmittance cut-off (prefix mask); t_incl is non-increasing along L, so
    # when the last entry is above the threshold nothing is cut.
    keep = None
    if t_min > 0 and bool(t_incl[..., -1].amin() <= t_min):
        keep = torch.sub(t_incl, t_min).mul_(_BIG).clamp_(0.0, 1.0)  # t_incl > t_min
        w.mul_(keep)
    if not need_all:
        return w
    return dict(one_m=one_m, t_excl=t_excl, keep=keep, w=w)


def _assemble(tile_vals: torch.Tensor, plan: RasterPlan) -> torch.Tensor:
    """[C * TY * TX, T*T, K] per-tile values -> [C, H, W, K] image (cropped)."""
    C, TY, TX, T = plan.n_cams, plan.tiles_y, plan.tiles_x, plan.tile
    K = tile_vals.shape[-1]
    img = tile_vals.reshape(C, TY, TX, T, T, K).permute(0, 1, 3, 2, 4, 5)
    img = img.reshape(C, TY * T, TX * T, K)
    return img[:, : plan.height, : plan.width]


def _disassemble(img: torch.Tensor, plan: RasterPlan) -> torch.Tensor:
    """[C, H, W, K] image -> [C * TY * TX, T*T, K] per-tile values (zero padded)."""
    C, TY, TX, T = plan.n_cams, plan.tiles_y, plan.tiles_x, plan.tile
    K = img.shape[-1]
    full = img.new_zeros(C, TY * T, TX * T, K)
    full[:, : plan.height, : plan.width] = img
    return full.reshape(C, TY, T, TX, T, K).permute(0, 1, 3, 2, 4, 5).reshape(C * TY * TX, T * T, K)


class _CompositeFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, mean2d, conic, opac, feat, smin, plan, alpha_max, t_min):
        consts = (alpha_max, t_min)
        with torch.no_grad():
            packed = torch.cat(
                [mean2d, conic, torch.log(opac)[:, None], smin[:, None]], dim=1
            ).contiguous()
            K = feat.shape[1]
            C, TY, TX, T = plan.n_cams, plan.tiles_y, plan.tiles_x, plan.tile
            out = feat.new_zeros(C * TY * TX, T * T, K)
            for ch in plan.chunks:
                B, L = ch.gidx.shape
                alpha, _ = _chunk_alpha(ch, packed, plan, consts[0])
                w = _blend_weights(alpha, consts[1], need_all=False).reshape(B, T * T, L)
                f = feat[ch.gidx.reshape(-1)].reshape(B, L, K)
                out[ch.tiles] = torch.bmm(w, f)
            img = _assemble(out, plan)
        ctx.save_for_backward(mean2d, conic, opac, feat, smin)
        ctx.plan = plan
        ctx.consts = consts
        return img

    @staticmethod
    def backward(ctx, grad_img):
        mean2d, conic, opac, feat, smin = ctx.saved_tensors
        plan = ctx.plan
        consts = ctx.consts
        T = plan.tile
        K = feat.shape[1]
        V = mean2d.shape[0]
        dt = mean2d.dtype
        with torch.no_grad():
            packed = torch.cat(
                [mean2d, conic, torch.log(opac)[:, None], smin[:, None]], dim=1
            ).contiguous()
            G_tiles = _disassemble(grad_img.to(dt), plan)  # [n_tiles, P, K]
            # per visible splat: d mx, d my, d a, d b, d c, d opacity, d feat[K]
            gacc = mean2d.new_zeros(V, 6 + K)
            lx, ly = _tile_local_coords(T, dt, mean2d.device)
            # polynomial basis of pixel (i = row, j = col) local coords: [6, P]
            LYg, LXg = torch.meshgrid(ly, lx, indexing="ij")
            LXf, LYf = LXg.reshape(-1), LYg.reshape(-1)
            phi = torch.stack([torch.ones_like(LXf), LXf, LYf, LXf * LXf, LXf * LYf, LYf * LYf])
            acc_mom, acc_feat, acc_ml, acc_idx, acc_valid = [], [], [], [], []
            for ch in plan.chunks:
                B, L = ch.gidx.shape
                G = G_tiles[ch.tiles]  # [B, P, K]
                if not bool(G.abs().amax() > 0):
                    continue
                alpha4, q = _chunk_alpha(ch, packed, plan, consts[0])
                tm = _blend_weights(alpha4, consts[1], need_all=True)
                f = feat[ch.gidx.reshape(-1)].reshape(B, L, K)
                P = T * T
                w = tm["w"].reshape(B, P, L)
                d_feat = torch.bmm(w.transpose(1, 2), G)  # [B, L, K]
                g = torch.bmm(G, f.transpose(1, 2))  # [B, P, L] = G . f_i
                cs = torch.cumsum(w * g, dim=-1)
                suffix = torch.sub(cs[..., -1:], cs)  # sum_{j > i} w_j g_j
                alpha = alpha4.reshape(B, P, L)
                one_m = tm["one_m"].reshape(B, P, L)
                # d out / d alpha_i = keep_i T_i g_i - suffix_i / (1 - alpha_i)
                d_alpha = tm["t_excl"].reshape(B, P, L) * g
                if tm["keep"] is not None:
                    d_alpha.mul_(tm["keep"].reshape(B, P, L))
                d_alpha.sub_(suffix.div_(one_m))
                # alpha = exp(s) inside the cut-off and below the clamp: d alpha / ds = alpha
                ds = d_alpha.mul_(alpha)
                if bool(alpha.amax() >= consts[0]):  # clamped entries have no gradient
                    ds.mul_(torch.rsub(alpha, consts[0]).mul_(_BIG).clamp_(0.0, 1.0))
                mom = torch.matmul(phi, ds)  # [B, 6, L]: sum_p ds * (1, lx, ly, lx^2, lx ly, ly^2)
                acc_mom.append(mom.transpose(1, 2).reshape(B * L, 6))
                acc_feat.append(d_feat.reshape(B * L, K))
                acc_ml.append(torch.stack([q["mlx"], q["mly"]], dim=-1).reshape(B * L, 2))
                acc_idx.append(ch.gidx.reshape(-1))
                acc_valid.append(ch.valid.reshape(-1))
            if acc_idx:
                # per-(tile, splat) moments -> gradients, once for all chunks
                mom = torch.cat(acc_mom)
                m0, mx1, my1, mxx, mxy, myy = mom.unbind(1)
                mlx, mly = torch.cat(acc_ml).unbind(1)
                idx = torch.cat(acc_idx)
                a, b, c = conic[idx].unbind(1)
                s_dx = mx1 - mlx * m0  # sum_p ds * dx, dx = px - mx (mlx: mean - tile centre)
                s_dy = my1 - mly * m0
                s_dxx = mxx - 2.0 * mlx * mx1 + mlx * mlx * m0
                s_dxy = mxy - mly * mx1 - mlx * my1 + mlx * mly * m0
                s_dyy = myy - 2.0 * mly * my1 + mly * mly * m0
                # s = log o - 0.5 (a dx^2 + 2 b dx dy + c dy^2)
                per = torch.cat([
                    torch.stack([a * s_dx + b * s_dy, b * s_dx + c * s_dy,
                                 -0.5 * s_dxx, -s_dxy, -0.5 * s_dyy, m0 / opac[idx]], dim=-1),
                    torch.cat(acc_feat),
                ], dim=-1)  # [sum B*L, 6 + K]
                per = per * torch.cat(acc_valid)[:, None]
                gacc.index_add_(0, idx, per)
        g_mean2d = gacc[:, 0:2] if ctx.needs_input_grad[0] else None
        g_conic = gacc[:, 2:5] if ctx.needs_input_grad[1] else None
        g_opac = gacc[:, 5] if ctx.needs_input_grad[2] else None
        g_feat = gacc[:, 6:] if ctx.needs_input_grad[3] else None
        return g_mean2d, g_conic, g_opac, g_feat, None, None, None, None


def composite(
    mean2d: torch.Tensor,
    conic: torch.Tensor,
    opacity: torch.Tensor,
    feat: torch.Tensor,
    smin: torch.Tensor,
    plan: RasterPlan,
    alpha_max: float,
    transmittance_min: float,
) -> torch.Tensor:
    """Composite V visible splats into ``[C, H, W, K]`` feature images.

    Args:
        mean2d: [V, 2] pixel coordinates (differentiable).
        conic: [V, 3] inverse 2D covariance (a, b, c) (differentiable).
        opacity: [V] in (0, 1] (differentiable).
        feat: [V, K] per-splat features, e.g. (r, g, b, z, 1) (differentiable).
        smin: [V] per-splat cut-off on s = log(opacity) - power (not differentiated).
        plan: tile lists from :func:`build_plan`.
    Returns:
        [C, H, W, K]: sum over the depth-sorted splats of w_i * feat_i.
    """
    V = mean2d.shape[0]
    if mean2d.shape != (V, 2) or conic.shape != (V, 3) or opacity.shape != (V,):
        raise ValueError(
            f"composite: expected mean2d [V,2], conic [V,3], opacity [V]; got "
            f"{list(mean2d.shape)}, {list(conic.shape)}, {list(opacity.shape)}"
        )
    if feat.ndim != 2 or feat.shape[0] != V or smin.shape != (V,):
        raise ValueError(f"composite: expected feat [V,K], smin [V]; got {list(feat.shape)}, {list(smin.shape)}")
    return _CompositeFn.apply(
        mean2d, conic, opacity, feat, smin.detach(), plan, float(alpha_max), float(transmittance_min)
    )
