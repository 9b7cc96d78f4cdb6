"""Rendering real data: the rope splats (framed camera) and the rope point cloud in the
four real RealSense cameras (checks the camera conventions against the object masks).
Also the Cameras helpers."""

from pathlib import Path

import numpy as np
import pytest
import torch

from soma_ros.core.cameras import Cameras, frame_points, look_at
from soma_ros.core.ply import load_splats, read_ply, read_splat, write_ply
from soma_ros.core.render import RenderConfig, render_splats

torch.set_num_threads(1)

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "real_rope_4view"
needs_data = pytest.mark.skipif(not DATA.exists(), reason="shared rope data not present")
ROPE_PNG = Path("/tmp/soma_rope_render.png")


def _save_png(path: Path, rgb: torch.Tensor) -> None:
    import cv2

    img = (rgb.detach().clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
    assert cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))


@needs_data
def test_rope_splats_render_from_ply(tmp_path):
    sp0 = read_splat(DATA / "gs_orig.splat")
    write_ply(tmp_path / "rope.ply", sp0)
    sp = load_splats(tmp_path / "rope.ply")
    assert len(sp) == 8957
    W, H = 640, 480
    cams = frame_points(sp.means, W, H)
    out = render_splats(sp, cams)
    assert out.rgb.shape == (1, H, W, 3)
    a = out.alpha[0]
    cover = (a > 0.5).float().mean().item()
    assert 0.03 < cover < 0.6, cover
    # framed: the object spans most of the image width and stays inside it
    cols = torch.nonzero((a > 0.5).any(0))[:, 0]
    rows = torch.nonzero((a > 0.5).any(1))[:, 0]
    assert cols.max() - cols.min() > 0.6 * W and cols.min() > 0 and cols.max() < W - 1
    assert rows.min() > 0 and rows.max() < H - 1
    # depth of covered pixels lies within the splats' depth range seen from the camera
    _, z = cams.project(sp.means)
    d = out.depth[0][a > 0.5]
    assert d.min() >= z.min() - 1e-4 and d.max() <= z.max() + 1e-4
    # the rope is tan/brown: red > green > blue on average over covered pixels
    c = (out.rgb[0][a > 0.5]).mean(0)
    assert c[0] > c[1] > c[2]
    # the .splat and the .ply give the same image
    out0 = render_splats(sp0, cams)
    assert (out0.rgb - out.rgb).abs().max() < 1e-4
    _save_png(ROPE_PNG, out.rgb[0])
    assert ROPE_PNG.stat().st_size > 1000


@needs_data
def test_point_cloud_in_real_cameras_matches_masks():
    import cv2

    K = np.load(DATA / "intr_list.npy")
    R = np.load(DATA / "R_list.npy")
    t = np.load(DATA / "t_list.npy")
    cams = Cameras.from_rt(K, R, t, 640, 480, names=[f"cam{i}" for i in range(4)])
    sp = read_ply(DATA / "pcd.ply")
    uv, z = cams.project(sp.means)
    assert (z > 0.3).all()
    out = render_splats(sp, cams.scaled(0.5), cfg=RenderConfig())
    assert out.alpha.shape == (4, 240, 320)
    for i in range(4):
        mask = cv2.imread(str(DATA / f"mask_{i}.png"), cv2.IMREAD_UNCHANGED) > 0
        u = uv[i].round().long().numpy()
        ok = (u[:, 0] >= 0) & (u[:, 0] < 640) & (u[:, 1] >= 0) & (u[:, 1] < 480)
        assert ok.all()
        assert mask[u[:, 1], u[:, 0]].mean() > 0.75  # projected object points land on the object
        m2 = cv2.resize(mask.astype(np.uint8), (320, 240), interpolation=cv2.INTER_NEAREST) > 0
        a = out.alpha[i].numpy() > 0.5
        iou = (a & m2).sum() / (a | m2).sum()
        assert iou > 0.45, (i, iou)


def test_cameras_helpers():
    K = torch.tensor([[100.0, 0, 32], [0, 110.0, 24], [0, 0, 1]])
    c2w = torch.stack([look_at([1.0, 2.0, 3.0], [0.0, 0.0, 0.0]), look_at([0.0, -1.0, 0.5], [0.0, 0.0, 0.0])])
    cams = Cameras.from_cam_to_world(torch.stack([K, K]), c2w, 64, 48, names=["a", "b"])
    torch.testing.assert_close(cams.centers(), torch.tensor([[1.0, 2.0, 3.0], [0.0, -1.0, 0.5]]))
    torch.testing.assert_close(cams.cam_to_world(), c2w.float(), atol=1e-6, rtol=0)
    # look_at: the target projects to the principal point, in front of the camera
    uv, z = cams.project(torch.zeros(1, 3))
    torch.testing.assert_close(uv[:, 0], torch.tensor([[32.0, 24.0], [32.0, 24.0]]), atol=1e-5, rtol=0)
    assert (z > 0).all()
    # world up (+z) appears up in the image (smaller row)
    uv_up, _ = cams.project(torch.tensor([[0.0, 0.0, 0.1]]))
    assert (uv_up[:, 0, 1] < 24.0).all()
    s = cams.select([1])
    assert len(s) == 1 and s.names == ["b"] and torch.equal(s.K[0], cams.K[1])
    assert cams.select(torch.tensor([False, True])).names == ["b"]
    half = cams.scaled(0.5)
    assert (half.width, half.height) == (32, 24)
    torch.testing.assert_close(half.K[0], torch.tensor([[50.0, 0, 16], [0, 55.0, 12], [0, 0, 1]]))
    # a point projects to half the pixel coordinates at half resolution
    p = torch.tensor([[0.05, -0.02, 0.03]])
    torch.testing.assert_close(half.project(p)[0], cams.project(p)[0] * 0.5)
    assert cams.to(dtype=torch.float64).K.dtype == torch.float64
    with pytest.raises(ValueError, match="names"):
        Cameras(K=K[None], world_to_cam=torch.eye(4)[None], width=4, height=4, names=["a", "b"])
    with pytest.raises(ValueError, match="K must be"):
        Cameras(K=torch.eye(4)[None], world_to_cam=torch.eye(4)[None], width=4, height=4)
    with pytest.raises(IndexError):
        cams.select([5])
    with pytest.raises(ValueError, match="parallel"):
        look_at([0, 0, 1.0], [0, 0, 0.0], up=[0, 0, 1.0])


def test_camera_info_k_converts_pixel_centres_and_scales_exactly():
    """CameraInfo centres pixel (col, row) at (col, row), the renderer at (col + 0.5, row + 0.5):
    the image centre of a 64x48 camera is (31.5, 23.5) in CameraInfo and (32, 24) here, and a
    resize scales the converted K exactly (cx of the 32x24 image: 16, not 15.75)."""
    from soma_ros.core.cameras import k_from_camera_info, k_to_camera_info

    ros = [100.0, 0, 31.5, 0, 110.0, 23.5, 0, 0, 1]
    K = k_from_camera_info(ros)
    np.testing.assert_allclose(K, [[100.0, 0, 32], [0, 110.0, 24], [0, 0, 1]])
    np.testing.assert_allclose(k_to_camera_info(torch.from_numpy(K)).ravel(), ros)
    np.testing.assert_allclose(k_from_camera_info(ros, 0.5, 0.5), [[50.0, 0, 16], [0, 55.0, 12], [0, 0, 1]])
