"""The live node's render process: the same images as the in-process render, a new scene size,
a dead child reported, nothing left in shared memory."""

import os
import signal
from pathlib import Path

import numpy as np
import pytest
import torch

from soma_ros.core.cameras import Cameras
from soma_ros.core.render import render
from soma_ros.core.scenes import synthetic_bundle
from soma_ros.live_render import RenderProcess, RenderProcessError


def _scene(n):
    b = synthetic_bundle(n, seed=1, width=96, height=72)
    s = b.splats
    from soma_ros.core.geometry import covariance_from_scale_rot

    covs = covariance_from_scale_rot(s.scales, s.quats)
    c = b.cameras[0]
    cams = Cameras.from_cam_to_world(np.stack([c.K, c.K]), np.stack([c.cam_to_sim, c.cam_to_sim]), c.width, c.height)
    return s, covs, cams


def _reference(s, covs, cams):
    out = render(s.means, covs, s.colors(), s.opacities, cams, background=torch.zeros(3))
    return (out.rgb.clamp(0, 1) * 255).round().to(torch.uint8).numpy(), out.depth.numpy()


def _shm_files():
    d = Path("/dev/shm")
    return {p.name for p in d.iterdir() if p.name.startswith("soma_render_")} if d.is_dir() else set()


def test_render_process_matches_in_process_render_bit_for_bit():
    before = _shm_files()
    s, covs, cams = _scene(800)
    with RenderProcess(cams.width, cams.height, len(cams), dtype=s.means.dtype) as rp:
        assert _shm_files() == before  # the buffer files are removed once both sides mapped them
        rp.set_scene(s.colors(), s.opacities)
        res = rp.render(s.means, covs, cams)
        rgb, depth = _reference(s, covs, cams)
        assert rgb.max() > 0  # the scene is in view
        assert np.array_equal(res.rgb, rgb) and np.array_equal(res.depth, depth)
        assert res.cpu_ms > 0 and res.wall_ms > 0
        # moved splats: the next render sees the new state
        moved = s.means + torch.tensor([0.02, 0.0, 0.0])
        res2 = rp.render(moved, covs, cams)
        assert not np.array_equal(res2.rgb, rgb)
        # a scene with another splat count gets new buffers
        s3, covs3, _ = _scene(300)
        rp.set_scene(s3.colors(), s3.opacities)
        res3 = rp.render(s3.means, covs3, cams)
        assert np.array_equal(res3.rgb, _reference(s3, covs3, cams)[0])
        with pytest.raises(ValueError, match="expected means"):
            rp.render(s.means, covs, cams)
    assert not rp.alive()


def test_dead_render_process_is_reported():
    s, covs, cams = _scene(200)
    rp = RenderProcess(cams.width, cams.height, len(cams), dtype=s.means.dtype)
    try:
        rp.set_scene(s.colors(), s.opacities)
        rp.render(s.means, covs, cams)
        os.kill(rp.pid, signal.SIGKILL)
        rp._proc.wait(5)
        with pytest.raises(RenderProcessError, match="not running|gone"):
            rp.render(s.means, covs, cams)
    finally:
        rp.close()


def test_render_process_rejects_bad_input():
    with pytest.raises(ValueError, match="positive"):
        RenderProcess(0, 10, 1)
    with pytest.raises(ValueError, match="float32 or float64"):
        RenderProcess(10, 10, 1, dtype=torch.float16)
