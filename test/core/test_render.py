"""Tests of the tile rasterizer against a dense brute-force reference, gradients, gsplat."""

import math

import pytest
import torch

from soma_ros.core.cameras import Cameras, look_at
from soma_ros.core.geometry import covariance_from_scale_rot, quat_normalize
from soma_ros.core.render import RenderConfig, eval_sh, gsplat_available, render, render_splats
from soma_ros.core.splats import Splats

torch.set_num_threads(1)


# ----------------------------------------------------------------- reference
def brute_force_render(means, covs, colors, opacities, cams: Cameras, bg, cfg: RenderConfig):
    """Dense per-pixel reference: every Gaussian at every pixel, depth-sorted, float64.

    Written independently of soma_ros.core.render (own projection, own compositing
    loop over the depth-sorted Gaussians, vectorised only over pixels).
    """
    dt = torch.float64
    means, covs, opacities = means.to(dt), covs.to(dt), opacities.to(dt)
    C, W, H = len(cams), cams.width, cams.height
    rgbs, depths, alphas = [], [], []
    for ci in range(C):
        col = (colors[ci] if colors.ndim == 3 else colors).to(dt)
        Rt = cams.world_to_cam[ci].to(dt)
        K = cams.K[ci].to(dt)
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        ys, xs = torch.meshgrid(torch.arange(H, dtype=dt) + 0.5, torch.arange(W, dtype=dt) + 0.5, indexing="ij")
        pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)  # [P, 2]
        P = pix.shape[0]
        entries = []
        for n in range(means.shape[0]):
            p = Rt[:3, :3] @ means[n] + Rt[:3, 3]
            x, y, z = p
            if not (cfg.near_plane < z < cfg.far_plane) or opacities[n] < cfg.alpha_min:
                continue
            tx, ty = x / z, y / z
            if cfg.clamp_jacobian:
                limx_p = (W - cx) / fx + 0.3 * (0.5 * W / fx)
                limx_n = cx / fx + 0.3 * (0.5 * W / fx)
                limy_p = (H - cy) / fy + 0.3 * (0.5 * H / fy)
                limy_n = cy / fy + 0.3 * (0.5 * H / fy)
                tx = torch.clamp(tx, -limx_n, limx_p)
                ty = torch.clamp(ty, -limy_n, limy_p)
            J = torch.zeros(2, 3, dtype=dt)
            J[0, 0] = fx / z
            J[0, 2] = -fx * tx / z
            J[1, 1] = fy / z
            J[1, 2] = -fy * ty / z
            S = J @ Rt[:3, :3] @ covs[n] @ Rt[:3, :3].T @ J.T + cfg.eps2d * torch.eye(2, dtype=dt)
            if torch.det(S) <= 0:
                continue
            mu = torch.stack([fx * x / z + cx, fy * y / z + cy])
            entries.append((float(z), n, mu, torch.linalg.inv(S), z))
        entries.sort(key=lambda e: e[0])  # front to back (stable)
        Tr = torch.ones(P, dtype=dt)
        done = torch.zeros(P, dtype=torch.bool)
        acc_c = torch.zeros(P, 3, dtype=dt)
        acc_d = torch.zeros(P, dtype=dt)
        acc_a = torch.zeros(P, dtype=dt)
        for _, n, mu, Si, z in entries:
            d = pix - mu
            power = 0.5 * (d @ Si * d).sum(-1)
            a_raw = opacities[n] * torch.exp(-power)
            inc = (power <= 0.5 * cfg.sigma_cutoff**2) & (a_raw >= cfg.alpha_min) & ~done
            a = torch.clamp(a_raw, max=cfg.alpha_max)
            nt = Tr * (1 - a)
            stop = inc & (nt <= cfg.transmittance_min)
            done = done | stop
            use = inc & ~stop
            w = torch.where(use, a * Tr, torch.zeros_like(a))
            acc_c = acc_c + w[:, None] * col[n]
            acc_d = acc_d + w * z
            acc_a = acc_a + w
            Tr = torch.where(use, nt, Tr)
        bgc = bg[ci] if bg is not None and bg.ndim == 2 else bg
        rgb = acc_c + (0 if bg is None else (1 - acc_a)[:, None] * bgc.to(dt))
        depth = torch.where(acc_a >= cfg.depth_alpha_eps, acc_d / acc_a.clamp_min(1e-300), torch.zeros_like(acc_d))
        rgbs.append(rgb.reshape(H, W, 3))
        depths.append(depth.reshape(H, W))
        alphas.append(acc_a.reshape(H, W))
    return torch.stack(rgbs), torch.stack(depths), torch.stack(alphas)


def random_scene(n, seed, dtype=torch.float64, spread=0.25, scale_range=(0.01, 0.08)):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 2 * spread
    means[:, 2] += 1.0
    lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=dtype) * (hi - lo) + lo)
    quats = quat_normalize(torch.randn(n, 4, generator=g, dtype=dtype))
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.95 + 0.04
    return means, scales, quats, colors, opac


def two_cameras(W, H, dtype=torch.float64):
    K = torch.tensor([[0.9 * W, 0, W / 2 + 0.7], [0, 0.9 * W, H / 2 - 0.4], [0, 0, 1]], dtype=dtype)
    c2w_a = torch.eye(4, dtype=dtype)
    c2w_b = look_at([0.5, -0.3, 0.1], [0.0, 0.0, 1.0], up=[0, -1, 0], dtype=dtype)
    return Cameras.from_cam_to_world(torch.stack([K, K * torch.tensor([[1.1], [1.0], [1]], dtype=dtype)]),
                                     torch.stack([c2w_a, c2w_b]), W, H, names=["a", "b"], dtype=dtype)


# ----------------------------------------------------------------- tests
# both compositors: the pure-torch reference and the compiled CPU kernels
RASTERS = pytest.mark.parametrize("raster", ["torch", "compiled"])


@RASTERS
@pytest.mark.parametrize("tile", [4, 8, 16])
def test_matches_brute_force(tile, raster):
    means, scales, quats, colors, opac = random_scene(60, seed=1)
    # a few splats at/behind the near plane and outside the image, and opaque ones
    means[0] = torch.tensor([0.0, 0.0, 0.005], dtype=torch.float64)
    means[1] = torch.tensor([5.0, 0.0, 1.0], dtype=torch.float64)
    opac[2:12] = 0.999  # hits the 0.99 clamp and the transmittance cut-off
    covs = covariance_from_scale_rot(scales, quats)
    cams = two_cameras(37, 29)
    cfg = RenderConfig(tile_size=tile, max_chunk_elems=2000, raster=raster)  # many chunks
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    out = render(means, covs, colors, opac, cams, background=bg, cfg=cfg)
    ref_rgb, ref_d, ref_a = brute_force_render(means, covs, colors, opac, cams, bg, cfg)
    assert out.rgb.shape == (2, 29, 37, 3) and out.depth.shape == (2, 29, 37) and out.alpha.shape == (2, 29, 37)
    assert ref_a.max() > 0.99 and (ref_a < 1e-6).any()  # scene has opaque and empty pixels
    torch.testing.assert_close(out.rgb, ref_rgb, atol=1e-9, rtol=0)
    torch.testing.assert_close(out.alpha, ref_a, atol=1e-9, rtol=0)
    torch.testing.assert_close(out.depth, ref_d, atol=1e-8, rtol=0)


@RASTERS
def test_matches_brute_force_float32_per_camera_colors_and_no_cull(raster):
    means, scales, quats, colors, opac = random_scene(80, seed=2)
    covs = covariance_from_scale_rot(scales, quats)
    cams = two_cameras(40, 24)
    cols = torch.stack([colors, colors.flip(1)])  # [C, N, 3]
    cfg = RenderConfig(tile_size=8, tile_cull=False, raster=raster)
    out = render(means.float(), covs.float(), cols.float(), opac.float(), cams.to(dtype=torch.float32), cfg=cfg)
    ref_rgb, ref_d, ref_a = brute_force_render(means, covs, cols, opac, cams, None, cfg)
    assert out.rgb.dtype == torch.float32
    assert (out.rgb.double() - ref_rgb).abs().max() < 1e-5
    assert (out.alpha.double() - ref_a).abs().max() < 1e-5
    assert ((out.depth.double() - ref_d).abs() * (ref_a > 1e-3)).max() < 1e-5


def test_empty_and_degenerate_inputs():
    cams = two_cameras(16, 16, dtype=torch.float32)
    z = torch.zeros(0, 3)
    out = render(z, torch.zeros(0, 3, 3), torch.zeros(0, 3), torch.zeros(0), cams,
                 background=torch.tensor([1.0, 0.0, 0.0]))
    assert out.alpha.abs().max() == 0 and out.depth.abs().max() == 0
    assert torch.all(out.rgb == torch.tensor([1.0, 0.0, 0.0]))
    # everything behind the camera
    m = torch.tensor([[0.0, 0.0, -1.0]])
    out = render(m, torch.eye(3)[None] * 1e-4, torch.ones(1, 3), torch.ones(1), cams.select([0]))
    assert out.alpha.max() == 0
    with pytest.raises(ValueError, match="covs must be"):
        render(m, torch.eye(3), torch.ones(1, 3), torch.ones(1), cams)
    with pytest.raises(ValueError, match="colors must be"):
        render(m, torch.eye(3)[None], torch.ones(2, 3), torch.ones(1), cams)
    with pytest.raises(ValueError, match="background"):
        render(m, torch.eye(3)[None], torch.ones(1, 3), torch.ones(1), cams, background=torch.ones(4))
    with pytest.raises(ValueError):
        RenderConfig(alpha_max=1.5)


def test_single_gaussian_analytic():
    """One isotropic splat on the optical axis: alpha at the centre pixel = opacity * exp(-power)."""
    W = H = 33
    K = torch.tensor([[50.0, 0, 16.5], [0, 50.0, 16.5], [0, 0, 1]], dtype=torch.float64)
    cams = Cameras(K=K, world_to_cam=torch.eye(4, dtype=torch.float64), width=W, height=H)
    s = 0.04
    covs = torch.eye(3, dtype=torch.float64)[None] * s * s
    out = render(torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64), covs,
                 torch.tensor([[1.0, 0.5, 0.25]], dtype=torch.float64), torch.tensor([0.8], dtype=torch.float64),
                 cams)
    var = (50.0 * s / 2.0) ** 2 + 0.3  # pixels^2
    # centre pixel (16, 16) has centre (16.5, 16.5) == principal point == projected mean
    assert out.alpha[0, 16, 16].item() == pytest.approx(0.8, abs=1e-12)
    # pixel 2 to the right: d = 2 px
    assert out.alpha[0, 16, 18].item() == pytest.approx(0.8 * math.exp(-0.5 * 4 / var), rel=1e-9)
    assert out.depth[0, 16, 16].item() == pytest.approx(2.0, abs=1e-12)
    torch.testing.assert_close(out.rgb[0, 16, 16], torch.tensor([0.8, 0.4, 0.2], dtype=torch.float64))
    # outside 3 sigma: exactly zero
    r = 3 * math.sqrt(var)
    assert out.alpha[0, 16, 16 + int(math.ceil(r)) + 1].item() == 0.0


@RASTERS
def test_gradients_match_finite_differences(raster):
    """torch.autograd.gradcheck (float64) through projection + tile compositing."""
    means, scales, quats, colors, opac = random_scene(7, seed=3, spread=0.2, scale_range=(0.05, 0.12))
    opac = opac.clamp(0.2, 0.9)
    W, H = 13, 11
    K = torch.tensor([[14.0, 0, 6.3], [0, 14.0, 5.4], [0, 0, 1]], dtype=torch.float64)
    cams = Cameras(K=K, world_to_cam=torch.eye(4, dtype=torch.float64), width=W, height=H)
    cfg = RenderConfig(tile_size=4, raster=raster)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)

    def fn(m, s, q, c, o):
        out = render(m, covariance_from_scale_rot(s, q), c, o, cams, background=bg, cfg=cfg)
        return out.rgb, out.depth, out.alpha

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, scales, quats, colors, opac))
    assert fn(*inputs)[2].max() > 0.5
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


@RASTERS
def test_gradients_opaque_scene_with_clamp_and_cutoff(raster):
    """gradcheck where alpha hits the 0.99 clamp and the transmittance cut-off fires."""
    means, scales, quats, colors, opac = random_scene(9, seed=8, spread=0.06, scale_range=(0.15, 0.3))
    opac = 0.996 + 0.0035 * torch.rand(9, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    W, H = 12, 10
    K = torch.tensor([[12.0, 0, 6.2], [0, 12.0, 4.9], [0, 0, 1]], dtype=torch.float64)
    # the front splat projects 0.1 px from the centre of pixel (6, 4): alpha there is clamped
    z0 = 0.9
    means[0] = torch.tensor([(6.6 - 6.2) * z0 / 12.0, (4.5 - 4.9) * z0 / 12.0, z0], dtype=torch.float64)
    cams = Cameras(K=K, world_to_cam=torch.eye(4, dtype=torch.float64), width=W, height=H)
    cfg = RenderConfig(tile_size=4, raster=raster)
    covs = covariance_from_scale_rot(scales, quats)
    # the scene exercises both rules: reference with them disabled differs
    ref = brute_force_render(means, covs, colors, opac, cams, None, cfg)
    no_cut = brute_force_render(means, covs, colors, opac, cams, None, RenderConfig(tile_size=4, transmittance_min=0.0))
    no_clamp = brute_force_render(means, covs, colors, opac, cams, None, RenderConfig(tile_size=4, alpha_max=0.9999))
    assert (ref[0] - no_cut[0]).abs().max() > 1e-5 and (ref[0] - no_clamp[0]).abs().max() > 1e-5

    def fn(m, c, o):
        out = render(m, covs, c, o, cams, cfg=cfg)
        return out.rgb, out.depth, out.alpha

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, colors, opac))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-7, atol=1e-6, rtol=1e-4)


@RASTERS
def test_gradients_wrt_covariance_entries(raster):
    means, scales, quats, colors, opac = random_scene(5, seed=4, spread=0.15, scale_range=(0.05, 0.1))
    covs = covariance_from_scale_rot(scales, quats)
    W, H = 10, 9
    K = torch.tensor([[11.0, 0, 5.1], [0, 11.0, 4.4], [0, 0, 1]], dtype=torch.float64)
    cams = Cameras(K=K, world_to_cam=torch.eye(4, dtype=torch.float64), width=W, height=H)
    cfg = RenderConfig(tile_size=4, raster=raster)
    weights = torch.randn(1, H, W, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def fn(cv):
        cv = 0.5 * (cv + cv.transpose(1, 2))
        out = render(means, cv, colors, opac, cams, cfg=cfg)
        return (torch.cat([out.rgb, out.depth[..., None], out.alpha[..., None]], -1) * weights).sum()

    assert torch.autograd.gradcheck(fn, (covs.clone().requires_grad_(True),), eps=1e-7, atol=1e-6, rtol=1e-4)


@RASTERS
def test_backward_float32_matches_float64(raster):
    means, scales, quats, colors, opac = random_scene(200, seed=5, scale_range=(0.005, 0.03))
    cams = two_cameras(48, 40)
    grads = {}
    for dt in (torch.float64, torch.float32):
        ins = [t.to(dt).clone().requires_grad_(True) for t in (means, scales, colors, opac)]
        covs = covariance_from_scale_rot(ins[1], quats.to(dt))
        out = render(ins[0], covs, ins[2], ins[3], cams.to(dtype=dt), cfg=RenderConfig(max_chunk_elems=4096, raster=raster))
        loss = (out.rgb ** 2).sum() + out.depth.sum() + out.alpha.sum()
        loss.backward()
        grads[dt] = [t.grad.double() for t in ins]
    for g64, g32 in zip(grads[torch.float64], grads[torch.float32]):
        assert torch.allclose(g32, g64, rtol=2e-3, atol=2e-3 * g64.abs().max())


def test_eval_sh_degree1_and_render_splats():
    n = 4
    sh_dc = torch.randn(n, 3, dtype=torch.float64) * 0.3
    sh_rest = torch.randn(n, 15, 3, dtype=torch.float64) * 0.2
    d = torch.nn.functional.normalize(torch.randn(n, 3, dtype=torch.float64), dim=-1)
    got = eval_sh(sh_dc, sh_rest, d, 1)
    c0, c1 = 0.28209479177387814, math.sqrt(3.0 / (4 * math.pi))
    exp = 0.5 + c0 * sh_dc - c1 * d[:, 1:2] * sh_rest[:, 0] + c1 * d[:, 2:3] * sh_rest[:, 1] - c1 * d[:, 0:1] * sh_rest[:, 2]
    torch.testing.assert_close(got, exp.clamp(0, 1))
    assert torch.equal(eval_sh(sh_dc, sh_rest, d, 0), (0.5 + c0 * sh_dc).clamp(0, 1))
    # degree 3 basis is orthonormal on the sphere: check sum_lm Y_lm(d)^2 = 16 / (4 pi)
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    ys = []
    for k in range(16):
        dc = torch.zeros(1, 3, dtype=torch.float64)
        rest = torch.zeros(1, 15, 3, dtype=torch.float64)
        if k == 0:
            dc[0, 0] = 1e-3
        else:
            rest[0, k - 1, 0] = 1e-3
        ys.append((eval_sh(dc, rest, dirs[:, None, :], 3)[:, 0, 0] - 0.5) / 1e-3)
    ys = torch.stack(ys, -1)
    torch.testing.assert_close((ys ** 2).sum(-1), torch.full((50,), 16 / (4 * math.pi), dtype=torch.float64))

    means, scales, quats, colors, opac = random_scene(30, seed=6)
    sp = Splats(means=means, quats=quats, scales=scales, opacities=opac, sh_dc=(colors - 0.5) / c0)
    cams = two_cameras(20, 16)
    out = render_splats(sp, cams)
    ref = render(means, covariance_from_scale_rot(scales, quats), sp.colors(), opac, cams)
    torch.testing.assert_close(out.rgb, ref.rgb)
    sp.sh_rest = torch.zeros(30, 3, 3, dtype=torch.float64)
    out1 = render_splats(sp, cams, sh_degree=None)  # degree 1 with zero rest == degree 0
    torch.testing.assert_close(out1.rgb, ref.rgb)


@pytest.mark.skipif(not (torch.cuda.is_available() and gsplat_available()),
                    reason="needs CUDA and gsplat")
def test_gsplat_matches_torch_path():
    means, scales, quats, colors, opac = random_scene(400, seed=7, dtype=torch.float32,
                                                       scale_range=(0.005, 0.04))
    covs = covariance_from_scale_rot(scales, quats)
    cams = two_cameras(96, 64, dtype=torch.float32)
    bg = torch.tensor([0.3, 0.3, 0.3])
    ref = render(means, covs, colors, opac, cams, background=bg, cfg=RenderConfig(backend="torch"))
    dev = torch.device("cuda")
    out = render(means.to(dev), covs.to(dev), colors.to(dev), opac.to(dev), cams.to(dev),
                 background=bg.to(dev), cfg=RenderConfig(backend="gsplat", tile_size=16))
    assert out.backend == "gsplat"
    # gsplat clamps alpha at 0.999 (ours 0.99) and has no 3-sigma pixel cut: compare loosely
    diff_rgb = (out.rgb.cpu() - ref.rgb).abs()
    diff_a = (out.alpha.cpu() - ref.alpha).abs()
    assert diff_rgb.mean() < 5e-3 and diff_a.mean() < 5e-3
    assert diff_rgb.max() < 0.1
    both = (ref.alpha > 0.5) & (out.alpha.cpu() > 0.5)
    assert ((out.depth.cpu() - ref.depth).abs()[both]).mean() < 2e-3
    # torch path on CUDA agrees with the torch path on CPU
    tcuda = render(means.to(dev), covs.to(dev), colors.to(dev), opac.to(dev), cams.to(dev),
                   background=bg.to(dev), cfg=RenderConfig(backend="torch"))
    assert (tcuda.rgb.cpu() - ref.rgb).abs().max() < 1e-4


def test_bench_render_smoke():
    from benchmarks.bench_render import bench_render, format_table, machine_description

    rows = bench_render(n_splats_list=(300,), resolutions=((64, 48),), device="cpu", repeats=1, warmup=0)
    assert len(rows) == 1
    r = rows[0]
    from soma_ros.core import raster_kernel

    expect = "compiled" if raster_kernel.available() else "torch"
    assert r["n_splats"] == 300 and (r["width"], r["height"]) == (64, 48) and r["backend"] == expect
    assert r["fwd_ms"] > 0 and r["fwdbwd_ms"] > 0 and r["peak_rss_mb"] > 0 and 0.1 < r["coverage"] < 1
    assert "64x48" in format_table(rows) and "cores" in machine_description()


def test_the_machine_is_named_by_its_cpu_model_and_torch():
    import os

    from soma_ros.core.machine import cpu_model, machine_description, machine_info

    info = machine_info()
    assert info["cpu"] == cpu_model() and info["cpu"].strip()
    assert info["torch"] == torch.__version__ and info["torch_threads"] == torch.get_num_threads()
    line = machine_description("cpu")
    assert line.startswith(cpu_model()) and f"{os.cpu_count()} cores" in line and line.endswith("device cpu")
    assert f"torch threads {torch.get_num_threads()} |" in line
    # another process's threads (a node the benchmark started) are named when given
    assert "torch threads 7 |" in machine_description("cpu", torch_threads=7)
