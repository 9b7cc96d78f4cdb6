"""Robot-to-simulation calibration: similarity transforms, table plane, gravity.

The paper's R2S mapping (Sec. 3 "Robot Conditioning" and appendix
"Transformation of Robot Conditioning") puts the metric robot into the
reconstruction ("simulation") frame with a similarity transform

    x_sim = s R x_rob + t,        T^ee_sim = [[s R, t], [0, 1]] T^ee_rob,

with (R, t) from the wrist camera, whose pose is known both in the robot frame
(URDF FK + hand-eye) and in the reconstruction frame, and the scale s from a
known reference size. Gravity comes from the fitted table plane, its sign
fixed by the camera viewing direction.

Everything here is numpy float64 (calibration is a one-off); :meth:`Sim3.apply_points`
and :func:`signed_distance_to_plane` also take torch tensors and keep their
dtype, device and autograd graph.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Optional, TypeVar, Union

import numpy as np
import torch

__all__ = [
    "Sim3",
    "sim3_from_camera_poses",
    "sim3_from_camera_pose_sets",
    "umeyama",
    "fit_table_plane",
    "signed_distance_to_plane",
    "gravity_direction",
    "gravity_from_camera",
]

ArrayT = TypeVar("ArrayT", np.ndarray, torch.Tensor)


def _as_np(x: Any, shape_tail: tuple[int, ...], what: str) -> np.ndarray:
    a = x.detach().cpu().numpy() if torch.is_tensor(x) else np.asarray(x)
    a = a.astype(np.float64)
    if a.shape[a.ndim - len(shape_tail):] != shape_tail or a.ndim < len(shape_tail):
        raise ValueError(f"{what} must have shape [..., {', '.join(map(str, shape_tail))}], got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} contains non-finite values")
    return a


def _check_rotation(R: np.ndarray, what: str, tol: float = 1e-6) -> None:
    if np.abs(R.T @ R - np.eye(3)).max() > tol or np.linalg.det(R) < 0:
        raise ValueError(f"{what} is not a rotation matrix (R^T R != I or det < 0)")


def _rigid_inv(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


@dataclass(frozen=True)
class Sim3:
    """Similarity transform x -> s R x + t (s > 0, R in SO(3), t [3]), numpy float64.

    ``compose``/``@``: ``(a @ b).apply_points(x) == a.apply_points(b.apply_points(x))``.
    """

    s: float
    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=np.float64)
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3):
            raise ValueError(f"Sim3.R must be [3, 3], got {R.shape}")
        if t.shape != (3,):
            raise ValueError(f"Sim3.t must be [3], got {t.shape}")
        if not (math.isfinite(self.s) and self.s > 0):
            raise ValueError(f"Sim3.s must be a positive finite scale, got {self.s}")
        _check_rotation(R, "Sim3.R")
        object.__setattr__(self, "s", float(self.s))
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    # ---------------------------------------------------------------- constructors
    @classmethod
    def identity(cls) -> "Sim3":
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, M: Any, tol: float = 1e-6) -> "Sim3":
        """From a 4x4 matrix [[s R, t], [0, 1]]; raises ValueError when it is not one."""
        M = _as_np(M, (4, 4), "Sim3 matrix")
        if M.shape != (4, 4):
            raise ValueError(f"Sim3 matrix must be [4, 4], got {M.shape}")
        if np.abs(M[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > tol:
            raise ValueError(f"Sim3 matrix must have last row [0, 0, 0, 1], got {M[3].tolist()}")
        A = M[:3, :3]
        det = np.linalg.det(A)
        if det <= 0:
            raise ValueError(f"Sim3 matrix has det(sR) = {det:.3g} <= 0 (reflection or degenerate)")
        s = det ** (1.0 / 3.0)
        R = A / s
        if np.abs(R.T @ R - np.eye(3)).max() > tol:
            raise ValueError("Sim3 matrix is not a uniform scale times a rotation (shear or anisotropic scale)")
        # re-orthonormalise to remove rounding
        U, _, Vt = np.linalg.svd(R)
        return cls(s, U @ Vt, M[:3, 3])

    def matrix(self) -> np.ndarray:
        """[[s R, t], [0, 1]] as a 4x4 float64 array (the paper's T_rob->sim)."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    def to_dict(self) -> dict[str, Any]:
        """Plain lists, for YAML/JSON."""
        return {"scale": self.s, "rotation": self.R.tolist(), "translation": self.t.tolist()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Sim3":
        for k in ("scale", "rotation", "translation"):
            if k not in d:
                raise ValueError(f"Sim3 dict is missing '{k}'")
        return cls(float(d["scale"]), np.asarray(d["rotation"], dtype=np.float64), np.asarray(d["translation"], dtype=np.float64))

    # ---------------------------------------------------------------- algebra
    def inverse(self) -> "Sim3":
        """x = (1/s) R^T (y - t)."""
        Rt = self.R.T
        return Sim3(1.0 / self.s, Rt, -(Rt @ self.t) / self.s)

    def compose(self, other: "Sim3") -> "Sim3":
        """self o other: apply `other` first, then `self`."""
        return Sim3(self.s * other.s, self.R @ other.R, self.s * (self.R @ other.t) + self.t)

    def __matmul__(self, other: "Sim3") -> "Sim3":
        return self.compose(other)

    # ---------------------------------------------------------------- application
    def apply_points(self, points: ArrayT) -> ArrayT:
        """Points [..., 3] -> s R p + t, same type (numpy, or torch keeping dtype/device/grad)."""
        if points.shape[-1:] != (3,):
            raise ValueError(f"points must have shape [..., 3], got {tuple(points.shape)}")
        if torch.is_tensor(points):
            R = torch.as_tensor(self.R, dtype=points.dtype, device=points.device)
            t = torch.as_tensor(self.t, dtype=points.dtype, device=points.device)
            return self.s * (points @ R.T) + t
        return self.s * (np.asarray(points, dtype=np.float64) @ self.R.T) + self.t

    def apply_directions(self, v: ArrayT) -> ArrayT:
        """Directions [..., 3] (unit vectors such as gravity or normals) -> R v (no scale, no shift)."""
        if v.shape[-1:] != (3,):
            raise ValueError(f"directions must have shape [..., 3], got {tuple(v.shape)}")
        if torch.is_tensor(v):
            return v @ torch.as_tensor(self.R, dtype=v.dtype, device=v.device).T
        return np.asarray(v, dtype=np.float64) @ self.R.T

    def apply_pose(self, T: ArrayT) -> ArrayT:
        """Rigid poses T_rob [..., 4, 4] -> rigid poses in the sim frame [..., 4, 4].

        Rotation R R_T, position s R p_T + t. The paper writes
        [[s R, t], [0, 1]] T, which has the same position column but a
        rotation block scaled by s; we return the orthonormal pose (a frame in
        the sim), i.e. ``matrix() @ T @ diag(1/s, 1/s, 1/s, 1)``.
        """
        if T.shape[-2:] != (4, 4):
            raise ValueError(f"poses must have shape [..., 4, 4], got {tuple(T.shape)}")
        if torch.is_tensor(T):
            R = torch.as_tensor(self.R, dtype=T.dtype, device=T.device)
            t = torch.as_tensor(self.t, dtype=T.dtype, device=T.device)
            out = T.clone()
            out[..., :3, :3] = R @ T[..., :3, :3]
            out[..., :3, 3] = self.s * (T[..., :3, 3] @ R.T) + t
            return out
        T = np.asarray(T, dtype=np.float64)
        out = T.copy()
        out[..., :3, :3] = self.R @ T[..., :3, :3]
        out[..., :3, 3] = self.s * (T[..., :3, 3] @ self.R.T) + self.t
        return out


def sim3_from_camera_poses(T_rob_cam: Any, T_rec_cam: Any, scale: float) -> Sim3:
    """Robot -> reconstruction similarity from one camera seen in both frames (paper appendix).

    T_rob_cam [4, 4]: camera-to-robot-base pose (metres), e.g. FK(q) @ T_ee_cam
    for the wrist camera. T_rec_cam [4, 4]: the same camera's camera-to-world
    pose in the reconstruction frame (e.g. from Pi3 / SfM), rigid, translation
    in reconstruction units. ``scale`` s = reconstruction units per metre.

    A point x_c (metres, camera frame) sits at x_rob = T_rob_cam x_c in the
    robot frame and at x_rec = T_rec_cam (s x_c) in the reconstruction, hence

        T_rob->sim = T_rec_cam diag(s, s, s, 1) (T_rob_cam)^-1,
        R = R_rec_cam R_rob_cam^T,   t = p_rec_cam - s R p_rob_cam.

    With s = 1 this is the paper's T_rec_cam (T_rob_cam)^-1.
    """
    A = _as_np(T_rob_cam, (4, 4), "T_rob_cam")
    B = _as_np(T_rec_cam, (4, 4), "T_rec_cam")
    if A.shape != (4, 4) or B.shape != (4, 4):
        raise ValueError(f"camera poses must be [4, 4], got {A.shape} and {B.shape}")
    _check_rotation(A[:3, :3], "T_rob_cam rotation", 1e-5)
    _check_rotation(B[:3, :3], "T_rec_cam rotation (must be rigid; put the scale in `scale`)", 1e-5)
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be positive and finite, got {scale}")
    M = B @ np.diag([scale, scale, scale, 1.0]) @ _rigid_inv(A)
    return Sim3.from_matrix(M, tol=1e-5)


def sim3_from_camera_pose_sets(
    T_rob_cam: Any, T_rec_cam: Any, scale: Optional[float] = None, axis_length_m: float = 0.1
) -> Sim3:
    """Least-squares robot -> reconstruction Sim3 from N corresponding camera poses [N, 4, 4].

    More robust than a single pose (:func:`sim3_from_camera_poses`) when the
    wrist camera was seen at several configurations, or several cameras are
    known in both frames. With ``scale`` known, each pose contributes its
    centre and three points ``axis_length_m`` metres along its camera axes
    (s * axis_length_m in the reconstruction), and a rigid fit recovers
    (R, t); one pose is then enough. With ``scale=None`` the scale is
    estimated from the camera centres alone (needs >= 3 non-collinear centres).
    """
    A = _as_np(T_rob_cam, (4, 4), "T_rob_cam")
    B = _as_np(T_rec_cam, (4, 4), "T_rec_cam")
    A = A.reshape(-1, 4, 4)
    B = B.reshape(-1, 4, 4)
    if A.shape != B.shape:
        raise ValueError(f"T_rob_cam and T_rec_cam must both be [N, 4, 4], got {A.shape} and {B.shape}")
    if scale is None:
        return umeyama(A[:, :3, 3], B[:, :3, 3], with_scale=True)
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be positive and finite, got {scale}")
    src = [A[:, :3, 3]] + [A[:, :3, 3] + axis_length_m * A[:, :3, k] for k in range(3)]
    dst = [B[:, :3, 3]] + [B[:, :3, 3] + scale * axis_length_m * B[:, :3, k] for k in range(3)]
    rigid = umeyama(scale * np.concatenate(src), np.concatenate(dst), with_scale=False)
    return Sim3(scale, rigid.R, rigid.t)


def umeyama(src: Any, dst: Any, with_scale: bool = True) -> Sim3:
    """Least-squares similarity (or rigid, with_scale=False) with dst ~ s R src + t.

    src, dst: corresponding points [N, 3], N >= 3, not all collinear
    (Umeyama 1991, closed form via the SVD of the cross-covariance).
    """
    X = _as_np(src, (3,), "src")
    Y = _as_np(dst, (3,), "dst")
    if X.ndim != 2 or X.shape != Y.shape:
        raise ValueError(f"src and dst must both be [N, 3], got {X.shape} and {Y.shape}")
    n = X.shape[0]
    if n < 3:
        raise ValueError(f"umeyama needs at least 3 point pairs, got {n}")
    mx, my = X.mean(0), Y.mean(0)
    Xc, Yc = X - mx, Y - my
    var_x = (Xc**2).sum() / n
    if var_x < 1e-18:
        raise ValueError("umeyama: the source points are all (nearly) identical")
    C = Yc.T @ Xc / n  # [3, 3] cross-covariance
    U, D, Vt = np.linalg.svd(C)
    if D[1] < 1e-12 * max(D[0], 1e-300):
        raise ValueError("umeyama: the points are collinear, the rotation is not determined")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_x) if with_scale else 1.0
    if s <= 0:
        raise ValueError("umeyama: degenerate correspondence (non-positive scale)")
    t = my - s * R @ mx
    return Sim3(s, R, t)


def fit_table_plane(
    points: Any,
    iters: int = 500,
    threshold: float = 0.01,
    seed: int = 0,
    max_score_points: int = 20000,
    return_inliers: bool = False,
) -> Union[tuple[np.ndarray, float], tuple[np.ndarray, float, np.ndarray]]:
    """Fit the dominant plane n . x + d = 0 (|n| = 1) with RANSAC + least-squares refit.

    points [N, 3]; ``threshold`` is the inlier distance (same units as the
    points); hypotheses are scored on at most ``max_score_points`` random
    points. The best hypothesis' inliers are refit by total least squares
    (smallest singular vector of the centred inliers), inliers are re-collected
    and refit once more. The sign of n is arbitrary (resolve it with
    :func:`gravity_direction`). Returns (n [3], d) or (n, d, inlier mask [N]).
    """
    P = _as_np(points, (3,), "points")
    if P.ndim != 2 or P.shape[0] < 3:
        raise ValueError(f"points must be [N, 3] with N >= 3, got {P.shape}")
    if iters < 1 or not threshold > 0:
        raise ValueError(f"need iters >= 1 and threshold > 0, got {iters}, {threshold}")
    rng = np.random.default_rng(seed)
    N = P.shape[0]
    S = P if N <= max_score_points else P[rng.choice(N, max_score_points, replace=False)]
    best_count, best = -1, None
    chunk = max(1, 2_000_000 // max(len(S), 1))
    for start in range(0, iters, chunk):
        k = min(chunk, iters - start)
        idx = rng.integers(0, N, size=(k, 3))  # repeated indices give a zero normal and are dropped
        tri = P[idx]  # [k, 3, 3]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        ln = np.linalg.norm(nrm, axis=1)
        ok = ln > 1e-12
        if not ok.any():
            continue
        nrm = nrm[ok] / ln[ok, None]
        d = -(nrm * tri[ok, 0]).sum(1)
        counts = (np.abs(S @ nrm.T + d) < threshold).sum(0)  # [k']
        i = int(counts.argmax())
        if counts[i] > best_count:
            best_count, best = int(counts[i]), (nrm[i], float(d[i]))
    if best is None:
        raise ValueError("fit_table_plane: all sampled point triples were collinear")
    n, d = best
    inl = np.abs(P @ n + d) < threshold
    for _ in range(2):
        if inl.sum() < 3:
            raise ValueError(f"fit_table_plane: only {int(inl.sum())} inliers within {threshold}")
        Q = P[inl]
        c = Q.mean(0)
        _, _, Vt = np.linalg.svd(Q - c, full_matrices=False)
        n = Vt[-1] / np.linalg.norm(Vt[-1])
        d = float(-n @ c)
        inl = np.abs(P @ n + d) < threshold
    if return_inliers:
        return n, d, inl
    return n, d


def signed_distance_to_plane(points: ArrayT, n: Any, d: float) -> ArrayT:
    """Signed distances [...] of points [..., 3] to the plane n . x + d = 0 (n normalised here).

    Positive on the side n points to. Torch in -> torch out (keeps grad).
    """
    if points.shape[-1:] != (3,):
        raise ValueError(f"points must have shape [..., 3], got {tuple(points.shape)}")
    n_np = _as_np(n, (3,), "plane normal").reshape(3)
    ln = float(np.linalg.norm(n_np))
    if ln < 1e-12:
        raise ValueError("plane normal has zero length")
    if torch.is_tensor(points):
        nt = torch.as_tensor(n_np / ln, dtype=points.dtype, device=points.device)
        return points @ nt + d / ln
    return np.asarray(points, dtype=np.float64) @ (n_np / ln) + d / ln


def gravity_direction(n: Any, view_dir: Any, min_cos: float = 1e-3) -> np.ndarray:
    """Unit gravity direction from the table normal and the camera viewing direction.

    ``view_dir`` is the camera's viewing direction in the same (world /
    reconstruction) frame as n: the optical axis, camera +z, pointing from
    the camera *into* the scene, i.e. the third column of the camera-to-world
    rotation. A camera that sees the table from above looks partly downwards,
    so gravity is the normal orientation that agrees with the view direction:

        g = sign(n . view_dir) n   ( = -sign(n . v_c) n with v_c = -view_dir )

    The paper writes g = -sign(n . v_c) n; that rule gives a downward g only
    when v_c points from the scene towards the camera, which is the
    convention it must use (with v_c = optical axis it would point g up,
    away from the table). Raises ValueError when the camera looks along the
    table (|cos| < min_cos), where the sign is undetermined.
    """
    nv = _as_np(n, (3,), "plane normal").reshape(3)
    vv = _as_np(view_dir, (3,), "view direction").reshape(3)
    ln, lv = np.linalg.norm(nv), np.linalg.norm(vv)
    if ln < 1e-12 or lv < 1e-12:
        raise ValueError("gravity_direction: zero-length normal or view direction")
    nv, vv = nv / ln, vv / lv
    cos = float(nv @ vv)
    if abs(cos) < min_cos:
        raise ValueError(
            f"gravity_direction: the camera views the table edge-on (|n . v| = {abs(cos):.2g}); the sign is undetermined"
        )
    return np.sign(cos) * nv


def gravity_from_camera(n: Any, T_world_cam: Any) -> np.ndarray:
    """:func:`gravity_direction` with the view direction taken from a camera-to-world pose [4, 4] or [3, 3]."""
    T = T_world_cam.detach().cpu().numpy() if torch.is_tensor(T_world_cam) else np.asarray(T_world_cam, dtype=np.float64)
    if T.shape not in ((4, 4), (3, 3)):
        raise ValueError(f"T_world_cam must be [4, 4] or [3, 3], got {T.shape}")
    return gravity_direction(n, T[:3, 2])
