"""Benchmark of the splat renderer: forward and forward+backward time, peak RSS.

Scene: a cloth-like object -- N splats on a wavy 0.3 m x 0.3 m sheet seen
from 0.55 m so that it fills ~60% of the image, in-plane std ~0.8x the splat
spacing (the sheet is fully covered, as a trained reconstruction is), thin
along the normal, opacities in [0.5, 1]. Worst case for the rasterizer is
dense coverage, which this is.

Usage: ``python -m benchmarks.bench_render [--device cpu] [--repeats 5] [--raster both]``
prints a table naming the machine and the load average; with ``--raster both``
(the default on CPU) the pure-torch reference and the compiled kernels are timed
on the same scenes and their ratios printed. :func:`bench_render` returns the
rows (used by ``soma bench core``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import time
from typing import Optional, Sequence

import torch

from soma_ros.core.cameras import Cameras, look_at
from soma_ros.core.geometry import covariance_from_scale_rot, quat_normalize
from soma_ros.core.machine import machine_description
from soma_ros.core.render import RenderConfig, render

__all__ = ["bench_render", "make_bench_scene", "machine_description"]


def make_bench_scene(n: int, width: int, height: int, device="cpu", seed: int = 0):
    """(means [n,3], scales [n,3], quats [n,4], colors [n,3], opacities [n], cameras)."""
    g = torch.Generator().manual_seed(seed)
    side = 0.3
    uv = (torch.rand(n, 2, generator=g) - 0.5) * side
    h = 0.02 * torch.sin(uv[:, 0] * 25.0) * torch.cos(uv[:, 1] * 18.0)
    means = torch.stack([uv[:, 0], uv[:, 1], h], dim=-1)
    spacing = side / math.sqrt(n)
    scales = torch.stack(
        [
            spacing * 0.8 * torch.exp(0.3 * torch.randn(n, generator=g)),
            spacing * 0.8 * torch.exp(0.3 * torch.randn(n, generator=g)),
            torch.full((n,), spacing * 0.1),
        ],
        dim=-1,
    )
    quats = quat_normalize(torch.tensor([1.0, 0.0, 0.0, 0.0]) + 0.15 * torch.randn(n, 4, generator=g))
    colors = torch.rand(n, 3, generator=g)
    opac = 0.5 + 0.5 * torch.rand(n, generator=g)
    f = 0.8 * width
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    c2w = look_at([0.0, -0.17, 0.36], [0.0, 0.0, 0.0], up=[0.0, 0.0, 1.0])
    cams = Cameras.from_cam_to_world(K, c2w, width, height, names=["bench"])
    return (means.to(device), scales.to(device), quats.to(device), colors.to(device),
            opac.to(device), cams.to(device))


def _reset_peak_rss() -> bool:
    try:  # Linux >= 4.0: writing 5 resets VmHWM of this process
        with open(f"/proc/{os.getpid()}/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float:
    try:
        with open(f"/proc/{os.getpid()}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _sync(device):
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def bench_render(
    n_splats_list: Sequence[int] = (1000, 4000, 13000),
    resolutions: Sequence[tuple[int, int]] = ((320, 240), (640, 480)),
    device: str = "cpu",
    repeats: int = 5,
    cfg: Optional[RenderConfig] = None,
    warmup: int = 1,
) -> list[dict]:
    """Time the renderer on :func:`make_bench_scene`; one row per (resolution, n).

    Each row: n_splats, width, height, device, backend, fwd_ms / fwdbwd_ms
    (median wall time over ``repeats``, plus min), fwd_cpu_ms / fwdbwd_cpu_ms
    (median process CPU time: the figure that holds on a shared machine), coverage
    (mean alpha), n_isect,
    peak_rss_mb (process VmHWM reset before the row; whole-process figure).
    """
    cfg = cfg or RenderConfig()
    rows = []
    for (w, h) in resolutions:
        for n in n_splats_list:
            means, scales, quats, colors, opac, cams = make_bench_scene(n, w, h, device)
            _reset_peak_rss()
            fwd, fb, fwd_cpu, fb_cpu = [], [], [], []
            out = None
            for i in range(warmup + repeats):
                _sync(device)
                t0, c0 = time.perf_counter(), time.process_time()
                with torch.no_grad():
                    covs = covariance_from_scale_rot(scales, quats)
                    out = render(means, covs, colors, opac, cams, cfg=cfg)
                _sync(device)
                t1, c1 = time.perf_counter(), time.process_time()
                m = means.clone().requires_grad_(True)
                s = scales.clone().requires_grad_(True)
                c = colors.clone().requires_grad_(True)
                o = opac.clone().requires_grad_(True)
                _sync(device)
                t2, c2 = time.perf_counter(), time.process_time()
                o2 = render(m, covariance_from_scale_rot(s, quats), c, o, cams, cfg=cfg)
                loss = o2.rgb.square().sum() + o2.depth.sum()
                loss.backward()
                _sync(device)
                t3, c3 = time.perf_counter(), time.process_time()
                if i >= warmup:
                    fwd.append((t1 - t0) * 1e3)
                    fb.append((t3 - t2) * 1e3)
                    fwd_cpu.append((c1 - c0) * 1e3)
                    fb_cpu.append((c3 - c2) * 1e3)
            for xs in (fwd, fb, fwd_cpu, fb_cpu):
                xs.sort()
            rows.append(dict(
                n_splats=n, width=w, height=h, device=str(device), backend=out.backend,
                fwd_ms=fwd[len(fwd) // 2], fwd_min_ms=fwd[0],
                fwdbwd_ms=fb[len(fb) // 2], fwdbwd_min_ms=fb[0],
                fwd_cpu_ms=fwd_cpu[len(fwd_cpu) // 2], fwdbwd_cpu_ms=fb_cpu[len(fb_cpu) // 2],
                coverage=float(out.alpha.mean()), n_isect=int(out.n_isect),
                peak_rss_mb=_peak_rss_mb(),
            ))
    return rows


def agreement_on_run(run_dir: str) -> dict:
    """Torch reference vs compiled kernels on a run's scene (RUN/scene) through its fixed cameras.

    Loss ``mean |rgb - shifted rgb| + mean depth`` with gradients with respect to means,
    covariances, colours and opacities. The float64 torch reference is the yardstick: the row
    holds the float64 compiled kernels' difference from it, and the float32 torch and float32
    compiled renders' differences from it (float32 is what training renders; the L1 loss's
    sign flips at near-zero residuals, so its float32 gradients differ from float64 by a few
    per cent whichever path computes them).
    """
    import numpy as np

    from soma_ros.core.scene_bundle import SceneBundle

    b = SceneBundle.load(os.path.join(run_dir, "scene"))
    fixed = [c for c in b.cameras if c.cam_to_sim is not None]
    if not fixed:
        raise ValueError(f"{run_dir}/scene has no fixed camera")
    cams = Cameras.from_cam_to_world(np.stack([c.K for c in fixed]), np.stack([c.cam_to_sim for c in fixed]),
                                     fixed[0].width, fixed[0].height, names=[c.name for c in fixed])
    sp = b.splats
    target = None

    def run(dt, raster):
        nonlocal target
        ins = [t.detach().to(dt).clone().requires_grad_(True)
               for t in (sp.means, sp.covariances(), sp.colors(), sp.opacities)]
        out = render(ins[0], ins[1], ins[2], ins[3], cams.to(dtype=dt), cfg=RenderConfig(raster=raster))
        if target is None:
            target = torch.roll(out.rgb.detach(), 2, dims=2)
        loss = (out.rgb - target.to(dt)).abs().mean() + out.depth.mean()
        loss.backward()
        return float(loss.detach()), out.rgb.detach().double(), [t.grad.double() for t in ins]

    lr, ir, gr = run(torch.float64, "torch")
    row = dict(splats=len(sp), cameras=len(fixed), width=cams.width, height=cams.height)
    for key, dt, raster in (("f64_compiled", torch.float64, "compiled"), ("f32_torch", torch.float32, "torch"),
                            ("f32_compiled", torch.float32, "compiled")):
        lo, im, gs = run(dt, raster)
        row[f"{key}_loss_rel_diff"] = abs(lo - lr) / abs(lr)
        row[f"{key}_image_max_abs_diff"] = float((im - ir).abs().max())
        for name, x, y in zip(("means", "covs", "colors", "opacities"), gr, gs):
            row[f"{key}_grad_{name}_rel_l2"] = float((x - y).norm() / x.norm())
    return row


def format_table(rows: list[dict]) -> str:
    hdr = (f"{'res':>9} {'splats':>7} {'fwd ms':>8} {'(min)':>7} {'(CPU)':>7} {'fwd+bwd ms':>11} {'(min)':>7} "
           f"{'(CPU)':>7} {'cover':>6} {'isect':>7} {'RSS MB':>7}")
    lines = [hdr]
    for r in rows:
        lines.append(
            f"{r['width']:>4}x{r['height']:<4} {r['n_splats']:>7} {r['fwd_ms']:>8.1f} {r['fwd_min_ms']:>7.1f} "
            f"{r['fwd_cpu_ms']:>7.1f} {r['fwdbwd_ms']:>11.1f} {r['fwdbwd_min_ms']:>7.1f} {r['fwdbwd_cpu_ms']:>7.1f} "
            f"{r['coverage']:>6.2f} {r['n_isect']:>7} {r['peak_rss_mb']:>7.0f}"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (CPU)")
    ap.add_argument("--tile", type=int, default=RenderConfig.tile_size)
    ap.add_argument("--splats", type=int, nargs="+", default=[1000, 4000, 13000])
    ap.add_argument("--raster", default="both", choices=["both", "auto", "torch", "compiled"],
                    help="CPU compositor (RenderConfig.raster); 'both' times torch and compiled and prints ratios")
    ap.add_argument("--json", dest="json_path", default=None, help="also write the rows to this JSON file")
    ap.add_argument("--agreement", metavar="RUN", default=None,
                    help="only compare torch and compiled (loss, images, gradients) on RUN/scene and exit")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.agreement:
        row = agreement_on_run(args.agreement)
        print(f"{args.agreement}: {row['splats']} splats, {row['cameras']} fixed camera(s) {row['width']}x{row['height']}")
        print("against the float64 torch reference:")
        for key in ("f64_compiled", "f32_torch", "f32_compiled"):
            print(f"  {key:<13} " + "  ".join(f"{k[len(key) + 1:]}={v:.2e}" for k, v in row.items()
                                              if k.startswith(key)))
        return
    print(machine_description(args.device))
    l1, l5, _ = os.getloadavg()
    print(f"load average {l1:.2f} {l5:.2f} on {os.cpu_count()} cores (before)")
    rasters = ["torch", "compiled"] if args.raster == "both" else [args.raster]
    if not str(args.device).startswith("cpu"):
        rasters = ["auto"]
    tables = {}
    for raster in rasters:
        rows = bench_render(n_splats_list=args.splats, device=args.device, repeats=args.repeats,
                            cfg=RenderConfig(tile_size=args.tile, raster=raster))
        tables[raster] = rows
        print(f"renderer backend {rows[0]['backend']} (raster {raster}), tile {args.tile}, median of {args.repeats}")
        print(format_table(rows))
    if len(tables) == 2:
        print("speed-up of compiled over torch (median wall times; CPU times in brackets)")
        print(f"{'res':>9} {'splats':>7} {'fwd':>7} {'fwd+bwd':>8}")
        for a, b in zip(tables["torch"], tables["compiled"]):
            print(f"{a['width']:>4}x{a['height']:<4} {a['n_splats']:>7} {a['fwd_ms'] / b['fwd_ms']:>6.1f}x "
                  f"{a['fwdbwd_ms'] / b['fwdbwd_ms']:>7.1f}x   (CPU time: {a['fwd_cpu_ms'] / b['fwd_cpu_ms']:.1f}x, "
                  f"{a['fwdbwd_cpu_ms'] / b['fwdbwd_cpu_ms']:.1f}x)")
    l1, l5, _ = os.getloadavg()
    print(f"load average {l1:.2f} {l5:.2f} on {os.cpu_count()} cores (after)")
    if args.json_path:
        with open(args.json_path, "w") as f:
            json.dump(dict(machine=machine_description(args.device), tile=args.tile, repeats=args.repeats,
                           rows=tables), f, indent=1)
        print(f"wrote {args.json_path}")


if __name__ == "__main__":
    main()
