"""Scripted manipulation plans: Cartesian TCP waypoints -> joint trajectories.

A plan is made from the object's *rest* geometry and the episode's random
stream only, never from the simulated state, so switching a physical effect
on leaves the robot's commanded trajectory unchanged.

Tasks (TCP = grasp centre, hand pointing down, fingers closing across the
object):

* ``lift``  descend onto the grasp point, close, lift straight up, hold.
* ``drag``  descend, close, raise a little, drag along the table, hold.
* ``fold``  (cloth) grasp a corner, carry it over the cloth to near the
  opposite corner, lower it, open and retreat.

Shapes: ``q_ref``/``qd_ref`` [S, n_arm] and ``gap_ref`` [S] at the physics
rate (S = frames * steps_per_frame), ``tcp_ref`` [S, 3].
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .config import ObjectConfig, RobotConfig, TaskMotionConfig
from .objects import ObjectGeometry
from .robot import ArmIK
from ..core.errors import WorldError

__all__ = ["Plan", "make_plan", "PlanError", "hand_rotation"]


class PlanError(WorldError):
    """The scripted motion could not be solved (unreachable pose)."""


@dataclass
class Segment:
    t0: float
    t1: float
    p0: np.ndarray
    p1: np.ndarray
    gap0: float
    gap1: float
    name: str


@dataclass
class Plan:
    task: str
    dt: float
    q_ref: np.ndarray  # [S, n_arm]
    qd_ref: np.ndarray  # [S, n_arm]
    gap_ref: np.ndarray  # [S] finger gap (m)
    tcp_ref: np.ndarray  # [S, 3]
    rot: np.ndarray  # [3, 3] hand orientation (constant)
    grasp_step: int  # grasp constraints switch on at this step
    release_step: Optional[int]  # ... and off here (fold), else None
    carry: tuple[int, int]  # steps of the carrying motion (slip onset is inside)
    grasp_point: np.ndarray  # [3] TCP at the grasp
    closing_axis: np.ndarray  # [3] world direction of the finger motion
    segments: list[Segment] = field(default_factory=list)
    ik_max_pos_err: float = 0.0
    ik_max_rot_err: float = 0.0

    def describe(self) -> dict:
        """JSON-friendly summary for the sidecar."""
        return {
            "task": self.task,
            "grasp_point": self.grasp_point.round(5).tolist(),
            "closing_axis": self.closing_axis.round(5).tolist(),
            "grasp_time": self.grasp_step * self.dt,
            "release_time": None if self.release_step is None else self.release_step * self.dt,
            "segments": [
                {"name": s.name, "t0": round(s.t0, 4), "t1": round(s.t1, 4), "p0": s.p0.round(5).tolist(),
                 "p1": s.p1.round(5).tolist(), "gap0": s.gap0, "gap1": s.gap1}
                for s in self.segments
            ],
            "ik_max_pos_err_m": self.ik_max_pos_err,
            "ik_max_rot_err_rad": self.ik_max_rot_err,
        }


def hand_rotation(rc: RobotConfig, closing_world: np.ndarray) -> np.ndarray:
    """Hand rotation [3, 3] with the approach axis pointing down and the fingers closing along ``closing_world``."""
    a_h = np.asarray(rc.approach_axis, float)
    c_h = np.asarray(rc.closing_axis, float)
    a_h /= np.linalg.norm(a_h)
    c_h /= np.linalg.norm(c_h)
    H = np.stack([a_h, c_h, np.cross(a_h, c_h)], axis=1)
    a_w = np.array([0.0, 0.0, -1.0])
    c_w = np.asarray(closing_world, float).copy()
    c_w[2] = 0.0
    c_w /= np.linalg.norm(c_w)
    W = np.stack([a_w, c_w, np.cross(a_w, c_w)], axis=1)
    return W @ H.T


def _minjerk(tau: np.ndarray) -> np.ndarray:
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)


def _horizontal_perp(v: np.ndarray) -> np.ndarray:
    p = np.array([-v[1], v[0], 0.0])
    n = np.linalg.norm(p)
    if n < 1e-9:
        return np.array([0.0, 1.0, 0.0])
    return p / n


def _grasp_choice(geom: ObjectGeometry, obj: ObjectConfig, task: str, rng: np.random.Generator, table_z: float):
    """(grasp TCP point [3], closing axis [3], extra dict) from the rest geometry."""
    pts = geom.points
    z = table_z + obj.grasp_height
    if geom.kind == "rope":
        n = len(pts)
        i = int(rng.integers(int(0.15 * n), int(0.85 * n) + 1))
        i = min(max(i, 1), n - 2)
        tangent = pts[i + 1] - pts[i - 1]
        p = np.array([pts[i, 0], pts[i, 1], z])
        return p, _horizontal_perp(tangent), {"vertex": i}
    if geom.kind == "cloth":
        centre = np.array([geom.center_xy[0], geom.center_xy[1], 0.0])
        if task == "fold":
            names = sorted(geom.keypoints)
            k = names[int(rng.integers(len(names)))]
            c = geom.keypoints[k]
            # Grasp slightly inside the corner so the pads hold cloth on both sides.
            inward = centre - np.array([c[0], c[1], 0.0])
            inward[2] = 0.0
            inward /= np.linalg.norm(inward)
            p = np.array([c[0], c[1], z]) + 0.012 * inward
            opposite = {"corner_00": "corner_11", "corner_11": "corner_00", "corner_10": "corner_01", "corner_01": "corner_10"}[k]
            return p, _horizontal_perp(inward), {"corner": k, "opposite": opposite, "inward": inward}
        # lift / drag: a random point on the border, held just inside the edge.
        nx, ny = obj.count
        border = [i * ny + j for i in range(nx) for j in range(ny) if i in (0, nx - 1) or j in (0, ny - 1)]
        v = border[int(rng.integers(len(border)))]
        c = pts[v]
        inward = centre - np.array([c[0], c[1], 0.0])
        inward[2] = 0.0
        inward /= np.linalg.norm(inward)
        p = np.array([c[0], c[1], z]) + 0.012 * inward
        return p, _horizontal_perp(inward), {"vertex": int(v)}
    if geom.kind == "doll":
        part = "torso" if rng.uniform() < 0.7 else "head"
        c = geom.keypoints[part]
        p = np.array([c[0], c[1], z])
        return p, _horizontal_perp(geom.main_axis), {"part": part}
    raise ValueError(f"no grasp rule for object kind '{geom.kind}'")


def _segments(task: str, p_grasp: np.ndarray, geom: ObjectGeometry, obj: ObjectConfig, extra: dict,
              motion: TaskMotionConfig, rng: np.random.Generator, T: float, open_gap: float) -> list[Segment]:
    u = lambda ab: float(rng.uniform(ab[0], ab[1]))  # noqa: E731
    closed = obj.grasp_gap
    hover = p_grasp + np.array([rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02), u(motion.hover_height)])
    segs: list[Segment] = []

    def add(f0, f1, a, b, g0, g1, name):
        segs.append(Segment(f0 * T, f1 * T, np.asarray(a, float), np.asarray(b, float), g0, g1, name))

    if task in ("lift", "drop"):  # drop: lifted as in lift, but sooner, then the fingers open over the table
        top = p_grasp + np.array([rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03), u(motion.lift_height)])
        add(0.0, 0.30, hover, p_grasp, open_gap, open_gap, "descend")
        add(0.30, 0.40, p_grasp, p_grasp, open_gap, closed, "close")
        if task == "lift":
            add(0.42, 0.85, p_grasp, top, closed, closed, "lift")
            add(0.85, 1.0, top, top, closed, closed, "hold")
        else:
            add(0.42, 0.70, p_grasp, top, closed, closed, "lift")
            add(0.70, 0.76, top, top, closed, open_gap, "open")
            add(0.76, 1.0, top, top, open_gap, open_gap, "hold")
    elif task == "drag":
        dist = u(motion.drag_distance)
        raised = p_grasp + np.array([0.0, 0.0, motion.drag_lift])
        # A direction that keeps the end in the reachable, visible part of the table.
        for _ in range(64):
            ang = rng.uniform(-np.pi, np.pi)
            end = raised + dist * np.array([np.cos(ang), np.sin(ang), 0.0])
            if 0.36 <= end[0] <= 0.68 and abs(end[1]) <= 0.22:
                break
        add(0.0, 0.30, hover, p_grasp, open_gap, open_gap, "descend")
        add(0.30, 0.40, p_grasp, p_grasp, open_gap, closed, "close")
        add(0.40, 0.47, p_grasp, raised, closed, closed, "raise")
        add(0.47, 0.90, raised, end, closed, closed, "drag")
        add(0.90, 1.0, end, end, closed, closed, "hold")
    elif task == "fold":
        if geom.kind != "cloth":
            raise ValueError("fold is a cloth task")
        far = geom.keypoints[extra["opposite"]]
        frac = u((0.75, 0.92))
        target = p_grasp + frac * (np.array([far[0], far[1], p_grasp[2]]) - p_grasp)
        target[2] = p_grasp[2] + 0.012
        mid = 0.5 * (p_grasp + target)
        mid[2] = p_grasp[2] + u(motion.fold_lift)
        retreat = target + np.array([0.0, 0.0, 0.06])
        add(0.0, 0.25, hover, p_grasp, open_gap, open_gap, "descend")
        add(0.25, 0.33, p_grasp, p_grasp, open_gap, closed, "close")
        add(0.35, 0.56, p_grasp, mid, closed, closed, "lift_over")
        add(0.56, 0.72, mid, target, closed, closed, "lay_down")
        add(0.72, 0.80, target, target, closed, open_gap, "open")
        add(0.80, 1.0, target, retreat, open_gap, open_gap, "retreat")
    else:
        raise ValueError(f"unknown task '{task}'")
    return segs


def _sample(segs: list[Segment], t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TCP positions [S, 3] and finger gaps [S] at times t [S] (holds between segments)."""
    pos = np.repeat(segs[0].p0[None], len(t), axis=0)
    gap = np.full(len(t), segs[0].gap0)
    for s in segs:
        after = t >= s.t0
        tau = (t[after] - s.t0) / max(s.t1 - s.t0, 1e-9)
        w = _minjerk(tau)
        pos[after] = s.p0 + w[:, None] * (s.p1 - s.p0)
        gap[after] = s.gap0 + w * (s.gap1 - s.gap0)
    return pos, gap


def make_plan(
    task: str,
    geom: ObjectGeometry,
    obj: ObjectConfig,
    rc: RobotConfig,
    ik: ArmIK,
    motion: TaskMotionConfig,
    rng: np.random.Generator,
    n_frames: int,
    fps: float,
    steps_per_frame: int,
    table_z: float,
) -> Plan:
    """Plan the episode's motion and solve IK at every physics step."""
    dt = 1.0 / (fps * steps_per_frame)
    T = (n_frames - 1) / fps
    S = (n_frames - 1) * steps_per_frame + 1
    p_grasp, closing, extra = _grasp_choice(geom, obj, task, rng, table_z)
    # Of the two finger orientations, take the one closer to the rest posture's hand orientation.
    _, R_rest = ik.fk(ik.rest)
    cands = [hand_rotation(rc, closing), hand_rotation(rc, -closing)]
    ang = [np.arccos(np.clip((np.trace(R_rest.T @ R) - 1) / 2, -1, 1)) for R in cands]
    k = int(np.argmin(ang))
    rot = cands[k]
    closing = closing if k == 0 else -closing
    segs = _segments(task, p_grasp, geom, obj, extra, motion, rng, T, rc.gripper.open_gap)
    t = np.arange(S) * dt
    tcp, gap = _sample(segs, t)
    q = np.zeros((S, len(rc.arm_joints)))
    first = ik.solve(tcp[0], rot, ik.rest, max_iter=500)
    if first.pos_err > 1e-3 or first.rot_err > 1e-2:
        raise PlanError(f"start pose unreachable (error {first.pos_err * 1000:.1f} mm, {np.degrees(first.rot_err):.1f} deg)")
    q_prev = first.q
    max_p = max_r = 0.0
    for i in range(S):
        r = ik.solve(tcp[i], rot, q_prev, max_iter=50)
        if r.pos_err > 1e-3 or r.rot_err > 1e-2:
            raise PlanError(f"IK failed at t={t[i]:.3f}s (error {r.pos_err * 1000:.1f} mm, {np.degrees(r.rot_err):.1f} deg)")
        if np.max(np.abs(r.q - q_prev)) > 0.05:
            raise PlanError(f"IK jumped at t={t[i]:.3f}s (max joint step {np.max(np.abs(r.q - q_prev)):.3f} rad)")
        q[i] = r.q
        q_prev = r.q
        max_p, max_r = max(max_p, r.pos_err), max(max_r, r.rot_err)
    qd = np.gradient(q, dt, axis=0)
    names = [s.name for s in segs]
    close_seg = segs[names.index("close")]
    grasp_step = int(round((close_seg.t0 + 0.7 * (close_seg.t1 - close_seg.t0)) / dt))
    release_step = None
    if "open" in names:
        release_step = int(round(segs[names.index("open")].t0 / dt))
    carry_names = [n for n in names if n in ("lift", "drag", "lift_over", "lay_down")]
    c0 = int(round(segs[names.index(carry_names[0])].t0 / dt))
    c1 = int(round(segs[names.index(carry_names[-1])].t1 / dt))
    return Plan(
        task=task,
        dt=dt,
        q_ref=q,
        qd_ref=qd,
        gap_ref=gap,
        tcp_ref=tcp,
        rot=rot,
        grasp_step=grasp_step,
        release_step=release_step,
        carry=(c0, c1),
        grasp_point=p_grasp,
        closing_axis=closing,
        segments=segs,
        ik_max_pos_err=max_p,
        ik_max_rot_err=max_r,
    )
