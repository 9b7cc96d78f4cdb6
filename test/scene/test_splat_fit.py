"""The photometric splat fit (soma_ros.scene.splat_fit): densification / pruning bounds, a fit of a
rendered scene from a perturbed start, view-dependent colour, the strict presets."""

from __future__ import annotations

import math

import pytest
import torch

from soma_ros.core.cameras import Cameras, look_at
from soma_ros.core.splats import Splats, view_dependent_colors
from soma_ros.scene.splat_fit import FitConfig, ParamState, densify_and_prune, fit_splats, load_fit_config


def _cloud(n: int, seed: int = 0) -> Splats:
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, 3, generator=g) * torch.tensor([0.2, 0.05, 0.02])
    cols = torch.rand(n, 3, generator=g)
    return Splats.from_points(pts, cols, scale=0.004, opacity=0.6, total_mass=0.05)


def test_densify_and_prune_keeps_the_count_within_bounds():
    sp = _cloud(400)
    cfg = FitConfig(max_splats=500, min_splats=50, grad_threshold=1e-3, dense_scale=1.5, min_opacity=0.005,
                    max_scale=20.0)
    spacing = 0.004
    st = ParamState(sp, cfg, 3, 0.2, spacing)
    # every splat "wants" to grow: the cap decides, the largest gradients first
    grad = torch.linspace(2e-3, 1e-2, 400)
    with torch.no_grad():
        st.p["log_scales"][:200] = math.log(0.001)  # small: cloned
        st.p["log_scales"][200:] = math.log(0.02)  # large (> 1.5 x spacing): split
    info = densify_and_prune(st, grad, cfg, spacing, torch.Generator().manual_seed(0))
    assert len(st) == 500 and info["clone"] + info["split"] == 100 and info["pruned"] == 0
    assert info["split"] == 100  # the largest gradients are the large splats
    smax = st.p["log_scales"].detach().exp().max(-1).values
    # split parents and children carry scale / 1.6; the untouched large ones keep theirs
    assert int(torch.isclose(smax, torch.tensor(0.02 / 1.6)).sum()) == 200
    assert all(st.p[k].shape[0] == 500 for k in st.p)
    # the optimiser state follows the rows
    assert all(p.shape[0] == 500 for g in st.opt.param_groups for p in g["params"])
    # no growth beyond max_splats, however large the gradients
    info = densify_and_prune(st, torch.full((500,), 1.0), cfg, spacing)
    assert len(st) == 500 and info["clone"] + info["split"] == 0
    # pruning: transparent splats go, but never below min_splats
    with torch.no_grad():
        st.p["logit_op"][:] = -12.0
        st.p["logit_op"][:20] = 0.0
    info = densify_and_prune(st, torch.zeros(500), cfg, spacing, grow=False)
    assert len(st) == 50 and info["pruned"] == 450
    assert int((torch.sigmoid(st.p["logit_op"].detach()) > 0.4).sum()) == 20  # the opaque ones were kept
    # oversized splats are pruned
    with torch.no_grad():
        st.p["logit_op"][:] = 2.0
        st.p["log_scales"][:10] = math.log(21 * spacing)
    densify_and_prune(st, torch.zeros(50), FitConfig(max_splats=500, min_splats=10), spacing, grow=False)
    assert len(st) == 40


def _scene_and_views(n: int = 300, size: tuple[int, int] = (96, 72)):
    from soma_ros.core.render import render_splats
    from soma_ros.scene.capture import CaptureViews

    g = torch.Generator().manual_seed(1)
    t = torch.linspace(0, 1, n)
    pts = torch.stack([0.2 * t - 0.1, 0.03 * torch.sin(6 * t), 0.005 * torch.randn(n, generator=g)], -1)
    cols = torch.stack([0.5 + 0.4 * torch.sin(30 * t), 0.4 + 0.3 * torch.cos(17 * t), 0.3 + 0.0 * t], -1)
    truth = Splats.from_points(pts, cols, scale=0.004, opacity=0.9)
    W, H = size
    K = torch.tensor([[80.0, 0, W / 2], [0, 80.0, H / 2], [0, 0, 1]])
    eyes = [(0.0, -0.25, 0.25), (0.2, -0.2, 0.2), (-0.2, -0.2, 0.2)]
    c2w = torch.stack([look_at(torch.tensor(e), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0])) for e in eyes])
    cams = Cameras.from_cam_to_world(K.expand(3, 3, 3), c2w, W, H)
    with torch.no_grad():
        out = render_splats(truth, cams)
    views = CaptureViews(out.rgb.clamp(0, 1), out.alpha > 0.5, cams, depth=torch.where(out.alpha > 0.5, out.depth,
                                                                                         torch.zeros_like(out.depth)))
    return truth, views


def test_fit_recovers_a_rendered_scene_from_a_perturbed_start():
    from soma_ros.core.metrics import masked_psnr
    from soma_ros.core.render import render_splats

    truth, views = _scene_and_views()
    g = torch.Generator().manual_seed(2)
    start = Splats(truth.means + 0.002 * torch.randn(truth.means.shape, generator=g), truth.quats,
                   truth.scales * 1.5, torch.full_like(truth.opacities, 0.5), torch.zeros_like(truth.sh_dc))
    cfg = FitConfig(iters=120, densify_from=40, densify_until=100, densify_every=30, grad_threshold=1e-4,
                    max_splats=420, sh_start=60, check_every=20, patience=0, crop_margin=4, lr_color=0.03)
    fitted = fit_splats(start, views, cfg, progress=False)
    assert len(start) <= len(fitted) <= 420 or len(fitted) < len(start)  # grown within the cap, or pruned
    assert len(fitted) <= 420
    counts = [h["splats"] for h in cfg.history if "splats" in h]
    assert max(counts) <= 420 and any(h.get("clone", 0) + h.get("split", 0) > 0 for h in cfg.history)

    def score(sp):
        with torch.no_grad():
            out = render_splats(sp, views.cameras, sh_degree=None)
        return float(masked_psnr(out.rgb, views.images, views.masks).mean())

    before, after = score(start), score(fitted)
    assert after > before + 8.0, (before, after)
    assert cfg.best["iter"] >= 0 and math.isfinite(cfg.best["psnr_check"])
    assert fitted.sh_rest.shape[1] in (0, 3)
    assert float(fitted.mass.sum()) == pytest.approx(float(start.mass.sum()), rel=1e-5)


def test_view_dependent_colors_match_the_sh_basis_and_carry_gradients():
    from soma_ros.core.render import eval_sh

    sp = _cloud(20)
    rest = torch.randn(20, 3, 3) * 0.3
    sp = Splats(sp.means, sp.quats, sp.scales, sp.opacities, sp.sh_dc, rest.requires_grad_(True))
    centres = torch.tensor([[0.0, -0.5, 0.3], [0.4, 0.1, 0.5]])
    col = view_dependent_colors(sp.means, sp.sh_dc, sp.sh_rest, centres)
    assert col.shape == (2, 20, 3)
    d = sp.means[None] - centres[:, None]
    d = d / d.norm(dim=-1, keepdim=True)
    assert torch.allclose(col, eval_sh(sp.sh_dc, rest, d, 1), atol=1e-6)
    assert not torch.allclose(col[0], col[1])  # seen from two places: two colours
    col.sum().backward()
    assert rest.grad is not None and rest.grad.abs().sum() > 0
    c0 = sp.colors_seen_from(centres, degree=0)
    assert torch.equal(c0[0], sp.colors()) and torch.equal(c0[1], sp.colors())
    with pytest.raises(ValueError, match="centres must be"):
        view_dependent_colors(sp.means, sp.sh_dc, sp.sh_rest, centres[0])


def test_fit_presets_load_strictly(tmp_path):
    from soma_ros.core.config import ConfigError

    cpu, quality = load_fit_config("cpu"), load_fit_config("quality")
    assert cpu.iters < quality.iters and cpu.max_splats <= quality.max_splats
    bad = tmp_path / "bad.yaml"
    bad.write_text("iters: 10\nlr_colour: 0.1\n")
    with pytest.raises(ConfigError, match="lr_colour: unknown key"):
        load_fit_config(bad)
    bad.write_text("iters: 10\nlam: 2.0\n")
    with pytest.raises(ConfigError, match="lam must lie"):
        load_fit_config(bad)
    with pytest.raises(FileNotFoundError, match="fit preset not found"):
        load_fit_config("no_such_preset")
