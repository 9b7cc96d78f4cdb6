"""Robot -> sim calibration: Sim3 algebra, camera-pose transform, umeyama, table plane, gravity sign."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from soma_ros.core.calibration import (
    Sim3,
    fit_table_plane,
    gravity_direction,
    gravity_from_camera,
    signed_distance_to_plane,
    sim3_from_camera_pose_sets,
    sim3_from_camera_poses,
    umeyama,
)
from soma_ros.core.robot import RobotModel

torch.set_num_threads(1)


def _rand_rot(rng: np.random.Generator) -> np.ndarray:
    Q, R = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(R))
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def _rand_sim3(rng: np.random.Generator) -> Sim3:
    return Sim3(float(rng.uniform(0.2, 5.0)), _rand_rot(rng), rng.normal(size=3))


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


# ---------------------------------------------------------------- Sim3
def test_sim3_roundtrips() -> None:
    rng = np.random.default_rng(0)
    a, b = _rand_sim3(rng), _rand_sim3(rng)
    x = rng.normal(size=(100, 3))
    np.testing.assert_allclose(a.inverse().apply_points(a.apply_points(x)), x, atol=1e-12)
    np.testing.assert_allclose((a @ b).apply_points(x), a.apply_points(b.apply_points(x)), atol=1e-12)
    np.testing.assert_allclose((a @ a.inverse()).matrix(), np.eye(4), atol=1e-12)
    m = Sim3.from_matrix(a.matrix())
    assert m.s == pytest.approx(a.s) and np.allclose(m.R, a.R) and np.allclose(m.t, a.t)
    np.testing.assert_allclose(a.matrix() @ np.c_[x, np.ones(100)].T, np.c_[a.apply_points(x), np.ones(100)].T, atol=1e-12)
    d = Sim3.from_dict(a.to_dict())
    np.testing.assert_allclose(d.matrix(), a.matrix())
    # torch in, torch out, gradients flow
    xt = torch.tensor(x, requires_grad=True)
    yt = a.apply_points(xt)
    assert torch.is_tensor(yt) and yt.dtype == torch.float64
    yt.sum().backward()
    assert xt.grad is not None
    np.testing.assert_allclose(yt.detach().numpy(), a.apply_points(x), atol=1e-12)


def test_sim3_apply_pose_matches_paper_form() -> None:
    rng = np.random.default_rng(1)
    a = _rand_sim3(rng)
    T = _pose(_rand_rot(rng), rng.normal(size=3))
    P = a.apply_pose(T)
    paper = a.matrix() @ T  # [[sR, t], [0, 1]] T^ee_rob
    np.testing.assert_allclose(P[:3, 3], paper[:3, 3], atol=1e-12)
    np.testing.assert_allclose(P[:3, :3] * a.s, paper[:3, :3], atol=1e-12)
    np.testing.assert_allclose(P[:3, :3].T @ P[:3, :3], np.eye(3), atol=1e-12)
    Pt = a.apply_pose(torch.tensor(np.stack([T, T])))
    np.testing.assert_allclose(Pt.numpy()[1], P, atol=1e-12)


def test_sim3_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="positive"):
        Sim3(-1.0, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="not a rotation"):
        Sim3(1.0, np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    M = np.eye(4)
    M[0, 0] = 2.0
    with pytest.raises(ValueError, match="anisotropic"):
        Sim3.from_matrix(M)


# ---------------------------------------------------------------- umeyama
def test_umeyama_recovers_random_similarity() -> None:
    rng = np.random.default_rng(2)
    for _ in range(5):
        gt = _rand_sim3(rng)
        src = rng.normal(size=(50, 3))
        est = umeyama(src, gt.apply_points(src))
        assert est.s == pytest.approx(gt.s, rel=1e-10)
        np.testing.assert_allclose(est.R, gt.R, atol=1e-10)
        np.testing.assert_allclose(est.t, gt.t, atol=1e-9)
    # with noise: still close; rigid mode returns s = 1
    gt = Sim3(1.0, _rand_rot(rng), rng.normal(size=3))
    src = rng.normal(size=(500, 3))
    est = umeyama(src, gt.apply_points(src) + rng.normal(scale=1e-3, size=(500, 3)), with_scale=False)
    assert est.s == 1.0
    np.testing.assert_allclose(est.R, gt.R, atol=1e-3)
    with pytest.raises(ValueError, match="collinear"):
        line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
        umeyama(line, line)
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(src[:2], src[:2])


# ---------------------------------------------------------------- camera-pose transform
def _wrist_camera_setup(seed: int):
    """Panda wrist camera (hand-eye T_ee_cam) and a ground-truth robot -> reconstruction Sim3."""
    rng = np.random.default_rng(seed)
    model = RobotModel.from_config("panda", dtype=torch.float64)
    T_ee_cam = _pose(_rand_rot(rng), np.array([0.05, 0.0, 0.04]))
    gt = _rand_sim3(rng)
    return model, T_ee_cam, gt, rng


def test_camera_pose_transform_maps_wrist_camera() -> None:
    model, T_ee_cam, gt, rng = _wrist_camera_setup(3)
    q = model.sample_q(2, torch.Generator().manual_seed(3))
    T_rob_cam = model.ee_pose(q).numpy() @ T_ee_cam  # [2, 4, 4] camera-to-robot-base, metres
    T_rec_cam = gt.apply_pose(T_rob_cam)  # what SfM / Pi3 would report (rigid, reconstruction units)
    est = sim3_from_camera_poses(T_rob_cam[0], T_rec_cam[0], scale=gt.s)
    np.testing.assert_allclose(est.matrix(), gt.matrix(), atol=1e-9)
    # the robot-frame wrist camera lands on the reconstruction-frame wrist camera, also at another q
    np.testing.assert_allclose(est.apply_pose(T_rob_cam), T_rec_cam, atol=1e-9)
    # a point 0.3 m in front of the camera: robot frame -> sim == reconstruction of the same point (scaled)
    x_cam = np.array([0.02, -0.01, 0.3, 1.0])
    x_rob = (T_rob_cam[0] @ x_cam)[:3]
    x_rec = (T_rec_cam[0] @ np.r_[gt.s * x_cam[:3], 1.0])[:3]
    np.testing.assert_allclose(est.apply_points(x_rob), x_rec, atol=1e-9)
    # scale 1: exactly the paper's T_rec_cam (T_rob_cam)^-1
    est1 = sim3_from_camera_poses(T_rob_cam[0], T_rec_cam[0], scale=1.0)
    np.testing.assert_allclose(est1.matrix(), T_rec_cam[0] @ np.linalg.inv(T_rob_cam[0]), atol=1e-9)
    # robot control points map through the same transform
    cp = model.control_points(q)
    cp_sim = est.apply_points(cp)
    assert cp_sim.shape == cp.shape
    with pytest.raises(ValueError, match="rigid"):
        sim3_from_camera_poses(T_rob_cam[0], gt.matrix() @ T_rob_cam[0], scale=gt.s)


def test_camera_pose_sets_robust_to_noise() -> None:
    model, T_ee_cam, gt, rng = _wrist_camera_setup(4)
    q = model.sample_q(40, torch.Generator().manual_seed(4))
    T_rob_cam = model.ee_pose(q).numpy() @ T_ee_cam
    T_rec_cam = gt.apply_pose(T_rob_cam)
    noisy = T_rec_cam.copy()
    noisy[:, :3, 3] += rng.normal(scale=0.002 * gt.s, size=(40, 3))  # 2 mm of pose noise
    single = [sim3_from_camera_poses(T_rob_cam[i], noisy[i], gt.s) for i in range(40)]
    multi = sim3_from_camera_pose_sets(T_rob_cam, noisy, scale=gt.s)
    est_s = sim3_from_camera_pose_sets(T_rob_cam, noisy, scale=None)  # scale from camera centres

    probe = model.control_points(q).reshape(-1, 3).numpy()  # where the transform is used

    def err(s: Sim3) -> float:
        return float(np.linalg.norm(s.apply_points(probe) - gt.apply_points(probe), axis=1).mean() / gt.s)

    assert err(multi) < 1e-3  # < 1 mm in metric units, from 2 mm per-pose noise
    assert err(multi) < 0.5 * np.median([err(s) for s in single])
    assert est_s.s == pytest.approx(gt.s, rel=0.02)
    # one pose with known scale reproduces the single-pose formula
    one = sim3_from_camera_pose_sets(T_rob_cam[:1], T_rec_cam[:1], scale=gt.s)
    np.testing.assert_allclose(one.matrix(), gt.matrix(), atol=1e-9)


# ---------------------------------------------------------------- table plane
def test_plane_fit_recovers_noisy_plane_with_outliers() -> None:
    rng = np.random.default_rng(5)
    n_true = rng.normal(size=3)
    n_true /= np.linalg.norm(n_true)
    d_true = 0.7
    u = np.cross(n_true, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n_true, u)
    ab = rng.uniform(-1, 1, size=(3000, 2))
    on = ab[:, :1] * u + ab[:, 1:] * v - d_true * n_true + rng.normal(scale=0.002, size=(3000, 1)) * n_true
    outliers = rng.uniform(-1.5, 1.5, size=(2000, 3))  # 40 % outliers
    pts = rng.permutation(np.concatenate([on, outliers]))
    n, d, inl = fit_table_plane(pts, iters=300, threshold=0.01, seed=1, return_inliers=True)
    if n @ n_true < 0:
        n, d = -n, -d
    assert np.degrees(np.arccos(min(1.0, n @ n_true))) < 0.2
    assert d == pytest.approx(d_true, abs=1e-3)
    assert 2900 <= inl.sum() <= 3000 + 200
    sd = signed_distance_to_plane(on, n, d)
    assert np.abs(sd).max() < 0.01
    sdt = signed_distance_to_plane(torch.tensor(on), n, d)
    assert torch.is_tensor(sdt) and np.allclose(sdt.numpy(), sd)
    # signed: positive on the side the normal points to
    assert signed_distance_to_plane(np.array([[0.0, 0, 0]]) + (1.0 - d_true) * n, n, d)[0] == pytest.approx(1.0, abs=2e-3)


def test_plane_fit_real_rope_capture() -> None:
    """Real 4-camera capture (rope lying on a table, world up = -z): gravity comes out +z."""
    data = Path(__file__).resolve().parents[3] / "shared" / "data" / "real_rope_4view"
    if not (data / "pcd.ply").is_file():
        pytest.skip("real_rope_4view capture not available")
    raw = (data / "pcd.ply").read_bytes()
    head = raw.index(b"end_header\n") + len(b"end_header\n")
    assert b"property double x" in raw[:head] and b"property uchar blue" in raw[:head]
    dt = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    v = np.frombuffer(raw[head:], dtype=dt)
    pts = np.stack([v["x"], v["y"], v["z"]], 1)
    n, d = fit_table_plane(pts, threshold=0.005)
    R = np.load(data / "R_list.npy")  # camera-to-world rotations
    for k in range(R.shape[0]):
        for sign in (1.0, -1.0):
            g = gravity_from_camera(sign * n, R[k])
            assert g[2] > 0.99  # +z is down in this capture


# ---------------------------------------------------------------- gravity
@pytest.mark.parametrize("normal_sign", [1.0, -1.0])
def test_gravity_sign_rule(normal_sign: float) -> None:
    """A camera above a table (world up = +z) looking down: gravity is -z whichever way n points."""
    n = normal_sign * np.array([0.0, 0.0, 1.0])
    view = np.array([0.3, 0.1, -0.8])  # optical axis: from the camera into the scene, downwards
    g = gravity_direction(n, view)
    np.testing.assert_allclose(g, [0.0, 0.0, -1.0])
    # the paper's form -sign(n . v_c) n with v_c pointing from the scene to the camera
    v_c = -view
    np.testing.assert_allclose(g, -np.sign(n @ v_c) * n)
    # flipped world (world up = -z, e.g. an OpenCV-style reconstruction): gravity +z
    np.testing.assert_allclose(gravity_direction(n, -view), [0.0, 0.0, 1.0])
    # from a camera-to-world pose: camera +z is the optical axis
    Rz = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # camera looking straight down
    np.testing.assert_allclose(gravity_from_camera(n, _pose(Rz, np.array([0, 0, 1.0]))), [0.0, 0.0, -1.0])


def test_gravity_edge_on_view_is_an_error() -> None:
    with pytest.raises(ValueError, match="edge-on"):
        gravity_direction(np.array([0.0, 0, 1]), np.array([1.0, 0, 0]))
