"""The physics prior's rod against the reference world's rope, hanging at rest from a hold.

    python -m benchmarks.rope_static_hang [--world-config world/default] [--young 1e6] \
        [--mass-scales 1,10] [--holds 3,8,10,13] [--run RUN | --config tiny_physics_rod [--bend 30]] \
        [--swing 1.5 [--swing-damping 0.01]] [--carry-velocity on|off]

Both start as the same straight, level rope (the world config's rope: length, segments, radius,
mass; ``--young`` replaces its Young's modulus) with no table under it, held at three consecutive
vertices from ``--holds`` (the first index of each), and settle under gravity:

* **world**: the reference world's flex rope (``soma_ros.world.objects.flexcomp_xml``, the world's
  timestep and solver), the held vertices pinned in place by the same soft ``connect`` equalities
  the world's grasp uses (:data:`soma_ros.world.scene.GRASP_SOLREF`), 5 s with the velocities
  damped 1% per step so that it comes to rest;
* **prior**: the physics prior (:func:`soma_ros.core.effects.physics.pbd_step`, on 1500 splats sampled in
  the rope's tube) with the hard grip on the nodes within its attach radius of the hold, 5 s of
  30 Hz steps. Its parameters and coefficients are a trained run's (``--run``) or a training
  config's physics term (``--config``, its bending then the world rope's own rho A / (4 E I));
  ``--bend`` sets the bending compliance. A heavier rope is
  ``PhysicsMods.mass``, as the discrepancy workflow's ``mass_scale`` sets it; in the world the
  flex's mass is multiplied.

``--swing SECONDS`` also releases both ropes from level and follows them that long, the world
with only its flex's own damping (as it runs in the datasets), the prior with ``--swing-damping``
(default: its own): both arms' end heights every 3 frames and the long arm's swing period (its
first two troughs). ``--carry-velocity`` sets the prior's setting of that name (each step from
its own end-of-step velocities; :class:`soma_ros.core.effects.physics.PhysicsPrior.Params`).

Printed per hold and mass scale: each arm's end (horizontal distance along the rope, height)
relative to the hold, and the mean / largest distance between the world's vertices and the
prior's centre line at the same arc length. Nothing here is trained or fitted: it asks whether the
prior's rod hangs as the world's rope does, with the rest of the model (the network, the cluster
hierarchy, the renderer) out of the way (docs/discrepancy.md, session 41).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Optional

import numpy as np

N_SPLATS = 1500
SETTLE_S = 5.0
PRIOR_DT = 1.0 / 30.0


@dataclass
class Hang:
    """One rope: vertices or centre-line points [M, 3] (``track``: [F + 1, M, 3], every frame of a swing
    from release) and their arc length at rest [M]."""

    points: np.ndarray
    arc: np.ndarray
    track: Optional[np.ndarray] = None


def _straight(obj, z: float) -> np.ndarray:
    n = obj.segments + 1
    return np.stack([np.linspace(-obj.length / 2, obj.length / 2, n), np.zeros(n), np.full(n, z)], 1)


def world_hang(world_cfg, obj, held: list[int], mass_scale: float, z: float = 1.0, swing_frames: int = 0) -> Hang:
    """The world's rope (``obj``: its ObjectConfig) pinned at vertices ``held``, settled (velocities
    damped 1% per step for :data:`SETTLE_S`); with ``swing_frames`` > 0 instead released from level and
    left undamped (as the world runs it) for that many frames at 30 Hz, every frame kept."""
    import mujoco

    from soma_ros.world.objects import ObjectGeometry, flexcomp_xml
    from soma_ros.world.scene import GRASP_SOLREF

    pts = _straight(obj, z)
    n = len(pts)
    geom = ObjectGeometry(kind="rope", dim=1, points=pts, elements=np.stack([np.arange(n - 1), np.arange(1, n)], 1))
    ph = world_cfg.physics
    xml = (f'<mujoco><option timestep="{ph.timestep:.12g}" integrator="{ph.integrator}" solver="{ph.solver}" '
           f'iterations="{ph.iterations}" ls_iterations="{ph.ls_iterations}"/><worldbody>'
           f'{flexcomp_xml(geom, obj, young=obj.young, mass=obj.mass * mass_scale, material=None)}</worldbody></mujoco>')
    spec = mujoco.MjSpec.from_string(xml)
    m0 = spec.compile()
    va = int(m0.flex_vertadr[0])
    bodies = [m0.body(int(m0.flex_vertbodyid[va + i])).name for i in range(n)]
    for i in held:
        e = spec.add_equality(name=f"hold_{i}", type=mujoco.mjtEq.mjEQ_CONNECT, objtype=mujoco.mjtObj.mjOBJ_BODY,
                              name1=bodies[i], name2="world")
        e.solref = list(GRASP_SOLREF)
        e.data[0:3] = [0.0, 0.0, 0.0]
        e.data[3:6] = pts[i]
    m = spec.compile()
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    track = None
    if swing_frames > 0:
        per = int(round(PRIOR_DT / m.opt.timestep))
        frames = [d.flexvert_xpos[va:va + n].copy()]
        for _ in range(swing_frames):
            for _ in range(per):
                mujoco.mj_step(m, d)
            frames.append(d.flexvert_xpos[va:va + n].copy())
        track = np.stack(frames)
    else:
        for _ in range(int(round(SETTLE_S / m.opt.timestep))):
            mujoco.mj_step(m, d)
            d.qvel[:] *= 0.99
    out = d.flexvert_xpos[va:va + n].copy()
    if not np.isfinite(out).all():
        raise RuntimeError("world_hang: the world's rope diverged")
    return Hang(out, pts[:, 0] - pts[0, 0], track)


def prior_hang(params, coef: dict, obj, held: list[int], mass_scale: float, z: float = 1.0, seed: int = 0,
               swing_frames: int = 0) -> Hang:
    """The physics prior's rope (``params``: PhysicsPrior.Params, ``coef``: its coefficients as
    tensors) held where the world's vertices ``held`` are, settled: its nodes [K, 3]; with
    ``swing_frames`` > 0 released from level for that many 30 Hz steps, every frame kept (its
    damping is ``coef["damping"]``: set it to compare with the world's undamped swing)."""
    import torch

    from soma_ros.core.effects.physics import Grasp, PhysicsMods, build_layout, pbd_step

    f64 = torch.float64
    rng = np.random.default_rng(seed)
    s = rng.uniform(-obj.length / 2, obj.length / 2, N_SPLATS)
    ang = rng.uniform(0.0, 2.0 * np.pi, N_SPLATS)
    rad = obj.radius * np.sqrt(rng.uniform(0.0, 1.0, N_SPLATS))
    x = torch.tensor(np.stack([s, rad * np.cos(ang), z + rad * np.sin(ang)], 1), dtype=f64)
    masses = torch.full((N_SPLATS,), obj.mass / N_SPLATS, dtype=f64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=f64)
    below = torch.tensor(10.0, dtype=f64)  # a table plane 10 m below: never touched
    lay = build_layout(x, masses, up, below, params)
    centre = torch.tensor(_straight(obj, z)[held].mean(0), dtype=f64)
    side = torch.tensor([0.0, 0.5 * obj.radius, 0.0], dtype=f64)
    cp = torch.stack([centre + side, centre - side])  # the fingers, closed across the rope
    xn = lay.rest.clone()
    held_nodes = (xn - centre).norm(dim=-1) <= params.attach_radius
    if not bool(held_nodes.any()):
        raise ValueError(f"prior_hang: no prior node within the attach radius {params.attach_radius} m of the hold")
    grasp: Optional[Grasp] = Grasp(held_nodes, xn - centre)
    vn = torch.zeros_like(xn)
    mods = PhysicsMods(mass=torch.tensor(mass_scale - 1.0, dtype=f64))
    gravity = torch.tensor([0.0, 0.0, -9.81], dtype=f64)
    c64 = {k: v.detach().to(f64) for k, v in coef.items()}
    frames = [xn.numpy().copy()]
    for _ in range(swing_frames if swing_frames > 0 else int(round(SETTLE_S / PRIOR_DT))):
        out = pbd_step(lay, xn, vn, gravity, up, below, PRIOR_DT, params, c64, cp, cp, grasp, mods,
                       return_velocity=params.carry_velocity)
        x1, grasp = out[0], out[1]
        vn = out[2] if params.carry_velocity else (x1 - xn) / PRIOR_DT  # as PhysicsPrior.forward starts its steps
        xn = x1
        if swing_frames > 0:
            frames.append(xn.numpy().copy())
    out = xn.numpy()
    if not np.isfinite(out).all():
        raise RuntimeError("prior_hang: the prior's rope diverged")
    return Hang(out, lay.rest[:, 0].numpy() - (-obj.length / 2), np.stack(frames) if swing_frames > 0 else None)


def swing_period(heights: np.ndarray, dt: float = PRIOR_DT) -> Optional[float]:
    """The time (s) between the first two troughs of an arm end's height over a swing [F + 1] (a trough:
    lower than both neighbours), or None with fewer than two."""
    h = np.asarray(heights, dtype=float)
    troughs = [i for i in range(1, len(h) - 1) if h[i] < h[i - 1] and h[i] <= h[i + 1]]
    return None if len(troughs) < 2 else (troughs[1] - troughs[0]) * dt


def compare(world: Hang, prior: Hang) -> tuple[float, float]:
    """(mean, largest) distance (m) between the world's vertices and the prior's centre line at the same
    rest arc length (the prior's nodes interpolated; vertices beyond its first / last node skipped)."""
    order = np.argsort(prior.arc)
    a, p = prior.arc[order], prior.points[order]
    inside = (world.arc >= a[0]) & (world.arc <= a[-1])
    at = np.stack([np.interp(world.arc[inside], a, p[:, k]) for k in range(3)], 1)
    d = np.linalg.norm(world.points[inside] - at, axis=1)
    return float(d.mean()), float(d.max())


def rod_bend_compliance(obj) -> float:
    """The rod prior's bending coefficient of the world's rope: rho A / (4 E I) (s^2/m^4; mass per
    length over four times the bending stiffness, I = pi r^4 / 4; ``_newton_project``)."""
    return (obj.mass / obj.length) / (4.0 * obj.young * np.pi * obj.radius ** 4 / 4.0)


def arm_ends(h: Hang, hold: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """([along, height] of the arm at arc 0, the same of the far arm), relative to the hold's centre."""
    lo, hi = h.points[int(np.argmin(h.arc))] - hold, h.points[int(np.argmax(h.arc))] - hold
    return np.array([lo[0], lo[2]]), np.array([hi[0], hi[2]])


def prior_from(run: Optional[Path], config: str, bend: Optional[float]):
    """(PhysicsPrior.Params, coefficients) of a trained run's physics term or a training config's."""
    if run is not None:
        from soma_ros.core.checkpoint import load_checkpoint

        sim = load_checkpoint(run / "checkpoint.pt" if run.is_dir() else run)
        terms = [m for n, m in sim.named_modules() if n.split(".")[-1] == "physics"]
        if not terms:
            raise ValueError(f"{run}: the model has no physics term")
        term = terms[0]
    else:
        from soma_ros.core.effects import EffectSpec, build_effect
        from trainer.config import load_train_config

        specs = [e for e in load_train_config(config).model_config().effects if EffectSpec.parse(e).name == "physics"]
        if not specs:
            raise ValueError(f"training config {config!r} has no physics term")
        term = build_effect(specs[0])
    params, coef = term.params, {k: v.detach() for k, v in term.coefficients().items()}
    if bend is not None:
        import torch

        coef["bend"] = torch.tensor(float(bend), dtype=torch.float64)
    return params, coef


def run_hangs(world_cfg: str, young: Optional[float], mass_scales: list[float], holds: list[int],
              run: Optional[Path], config: str, bend: Optional[float], out=print, swing_s: float = 0.0,
              swing_damping: Optional[float] = None, carry_velocity: Optional[bool] = None) -> list[dict]:
    """Every hang (module docstring): one row per mass scale and hold. ``swing_s`` > 0: also released
    from level and followed for that long, the world undamped, the prior with ``swing_damping``
    (1/s; None: its own), both arms' end heights printed every 3 frames and each long arm's swing
    period (:func:`swing_period`) added to the row. ``carry_velocity``: the prior's setting of that
    name (None: the run's or config's)."""
    import torch

    from soma_ros.world.config import load_world_config

    wc = load_world_config(world_cfg)
    if "rope" not in wc.objects:
        raise ValueError(f"world config {world_cfg}: no rope object")
    obj = wc.objects["rope"]
    if young is not None:
        obj = replace(obj, young=float(young))
    n = obj.segments + 1
    bad = [h for h in holds if not 0 <= h <= n - 3]
    if bad:
        raise ValueError(f"--holds: the first held vertex must be in 0..{n - 3} (three are held), got {bad}")
    params, coef = prior_from(run, config, bend)
    if run is None and bend is None and params.bend_model == "rod":
        coef["bend"] = torch.tensor(rod_bend_compliance(obj), dtype=torch.float64)  # the world rope's own rho A / (4 E I)
    if carry_velocity is not None:
        params = replace(params, carry_velocity=bool(carry_velocity))
    out(f"rope {obj.length} m, {obj.segments} segments, radius {obj.radius} m, mass {obj.mass} kg, Young {obj.young:g} Pa; "
        f"prior: {params.bend_model} bending {float(coef['bend']):.4g}, grip {float(coef['grip']):.3g}, "
        f"stretch {float(coef['stretch']):.3g}, attach radius {params.attach_radius} m, carry_velocity {params.carry_velocity}")
    rows = []
    for ms in mass_scales:
        for h0 in holds:
            held = [h0, h0 + 1, h0 + 2]
            w = world_hang(wc, obj, held, ms)
            p = prior_hang(params, coef, obj, held, ms)
            hold = _straight(obj, 1.0)[held[1]]
            (wa, wb), (pa, pb) = arm_ends(w, hold), arm_ends(p, hold)
            mean, worst = compare(w, p)
            seg = np.linalg.norm(np.diff(w.points, axis=0), axis=1)
            rows.append({"mass_scale": ms, "held": held, "world_ends": [wa.tolist(), wb.tolist()],
                         "prior_ends": [pa.tolist(), pb.tolist()], "mean_m": mean, "max_m": worst})
            f = lambda e: f"({e[0]:+.3f}, {e[1]:+.3f})"  # noqa: E731
            out(f"mass x{ms:g} held {held}: world arms {f(wa)} {f(wb)}  prior {f(pa)} {f(pb)}  "
                f"distance mean {1e3 * mean:.1f} mm, max {1e3 * worst:.1f} mm  (world segments "
                f"{1e2 * seg.min():.2f}-{1e2 * seg.max():.2f} cm, rest {1e2 * obj.length / obj.segments:.2f})")
            if swing_s > 0:
                rows[-1].update(_swing(wc, obj, params, coef, held, ms, swing_s, swing_damping, hold, out))
    return rows


def _swing(wc, obj, params, coef: dict, held: list[int], ms: float, seconds: float, damping: Optional[float],
           hold: np.ndarray, out) -> dict:
    """Release from level (run_hangs' ``swing_s``): prints the arms' end heights, returns the long arm's
    periods {"world_period_s", "prior_period_s"} (None: fewer than two troughs)."""
    import torch

    frames = int(round(seconds / PRIOR_DT))
    c = dict(coef)
    if damping is not None:
        c["damping"] = torch.tensor(float(damping), dtype=torch.float64)
    w = world_hang(wc, obj, held, ms, swing_frames=frames)
    p = prior_hang(params, c, obj, held, ms, swing_frames=frames)
    long_first = hold[0] > 0.0  # the arm from arc 0 is the longer one when the hold is past the middle
    res = {}
    for name, h in (("world", w), ("prior", p)):
        ends = [int(np.argmin(h.arc)), int(np.argmax(h.arc))]
        for k, e in enumerate(ends):
            z = h.track[:, e, 2] - hold[2]
            out(f"    {name} {'first' if k == 0 else 'last '} arm's end, height (cm) every 3 frames: "
                + " ".join(f"{100 * v:+5.1f}" for v in z[::3]))
        z_long = h.track[:, ends[0 if long_first else 1], 2]
        res[f"{name}_period_s"] = swing_period(z_long)
    fmt = lambda v: "none" if v is None else f"{v:.2f} s"  # noqa: E731
    out(f"    long arm's swing period (first two troughs): world {fmt(res['world_period_s'])}, "
        f"prior {fmt(res['prior_period_s'])} (damping {float(c['damping']):g} /s)")
    return res


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.rope_static_hang", description=__doc__.split("\n\n")[0])
    ap.add_argument("--world-config", default="world/default")
    ap.add_argument("--young", type=float, default=None, help="the rope's Young's modulus (Pa; default: the config's)")
    ap.add_argument("--mass-scales", default="1,10")
    ap.add_argument("--holds", default="3,8,10,13", help="first of the three held vertices, per hang")
    ap.add_argument("--run", type=Path, default=None, help="a trained run whose physics term to use")
    ap.add_argument("--config", default="tiny_physics_rod", help="else: a training config's physics term")
    ap.add_argument("--bend", type=float, default=None,
                    help="the prior's bending compliance (default: the run's; with --config, the world rope's rho A / (4 E I))")
    ap.add_argument("--swing", type=float, default=0.0, metavar="SECONDS",
                    help="also release each rope from level and follow it this long, undamped in the world")
    ap.add_argument("--swing-damping", type=float, default=None, metavar="PER_S",
                    help="the prior's damping during --swing (default: its own)")
    ap.add_argument("--carry-velocity", choices=("on", "off"), default=None,
                    help="the prior's carry_velocity (default: the run's or config's)")
    a = ap.parse_args(argv)
    try:
        try:
            scales = [float(v) for v in a.mass_scales.split(",")]
            holds = [int(v) for v in a.holds.split(",")]
        except ValueError:
            raise ValueError("--mass-scales and --holds are comma-separated numbers") from None
        if min(scales) <= 0.1:  # PhysicsMods.mass > -0.9
            raise ValueError(f"--mass-scales: each must be > 0.1, got {scales}")
        if a.swing < 0 or (a.swing_damping is not None and a.swing_damping < 0):
            raise ValueError("--swing and --swing-damping must be >= 0")
        run_hangs(a.world_config, a.young, scales, holds, a.run, a.config, a.bend, swing_s=a.swing,
                  swing_damping=a.swing_damping,
                  carry_velocity=None if a.carry_velocity is None else a.carry_velocity == "on")
    except (ValueError, FileNotFoundError) as e:
        print(f"rope_static_hang: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
