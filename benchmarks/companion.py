"""Physics companion: a reduced position-based spring twin of a rope or cloth, used to measure
whether a crude physical model's *response* to an effect transfers to the reference world
(:mod:`benchmarks.discrepancy_companion`). Not part of the simulator.

The question it answers
-----------------------
The discrepancy workflow (issue #8) needs a model whose change under a candidate effect
predicts how measured episodes differ from effect-free ones. The learned network does not
respond physically to terms it never saw (docs/discrepancy.md). An alternative is a physics
channel: simulate each episode twice with a small twin, once nominal and once with the
effect, and add the *difference*, carried to the splats, to the learned rollout:

    x_splat(t) = x_learned(t) + [skin(x_effect(t)) - skin(x_nominal(t))]

The difference is exactly zero for a zero effect and the twin's own error cancels to first
order -- but only if the twin's response to the effect resembles the world's. The study
measures that with the evaluation-only ground truth (fraction of the world's effect
displacement the differential explains).

Model (per episode; batched over B episodes or parameter copies)
----------------------------------------------------------------
* **Nodes**: K farthest-point samples of the episode's initial points (the first is the
  point nearest the centroid); equal masses.
* **Constraints** (XPBD distance constraints, Jacobi passes with over-relaxation):
  stretch -- each node and its ``neighbors`` nearest within ``spring_radius_factor`` x the
  median nearest-node spacing; bending -- the next ``bend_neighbors`` nodes out to
  ``bend_radius_factor`` x spacing. Compliances per unit rest length (s^2).
* **Gravity**, still-air damping ``exp(-drag h)`` per substep and the **table**: a node may
  not go below its initial height above the plane (capped at ``contact_offset_max``);
  pushed below, it is projected back and its tangential displacement is reduced by Coulomb
  friction ``mu * depth``.
* **Gripper**: when the gripper state drops below ``grip_threshold`` (0 = closed), the nodes
  within ``attach_radius`` of the control points' centroid are attached (compliance
  ``grip_compliance``) at their offset to their nearest control point; opening releases
  them. Control points push free nodes out of ``contact_radius``.
* ``substeps`` per frame; any compliance stays stable.

Effects (:data:`EFFECT_TERMS`; one tensor per name, [B] or [B, 3], 0 = no change)
-------------------------------------------------------------------------------
=================  ========  =============================================================
name               shape     change
=================  ========  =============================================================
wind               [B, 3]    a force per unit mass (m/s^2): uniform (``wind_form`` "field"),
                             or "pressure": only its component along the local surface
                             normal (sheet) or across the local tangent (line) acts
linear_drag        [B]       ``-b v`` (1/s)
quadratic_drag     [B]       ``-q |v| v`` (1/m)
table_friction     [B]       the table's friction coefficient ``mu + dmu`` (>= 0)
gripper_slip       [B]       the grip saturates: each held node's correction is divided by
                             ``1 + s |dg| / (f_0 h^2)``, f_0 = g K / K_held (the object's
                             weight shared by the held nodes): it carries about ``1 / s``
                             times the weight (s >= 0)
mass_scale         [B]       the object is ``1 + e`` times heavier (inverse mass scaled in
                             the constraints and the grip; e > -0.9)
stiffness_scale    [B]       stretch and bending are ``1 + k`` times stiffer (compliances
                             divided by it; k > -0.9)
=================  ========  =============================================================

Shapes: ``rest`` [B, K, 3], constraints [B, E] (padded, ``kind`` 0), actions: control points
[B, T, P, 3] and gripper [B, T]; :meth:`Companion.rollout` returns nodes [B, F, K, 3],
:meth:`Companion.skin` carries them to the N points [B, F, N, 3].
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Optional, Sequence

import torch
from torch import nn

from soma_ros.core.spring_mass import farthest_point_sampling, neighbour_pairs, skin_weights

__all__ = ["CompanionConfig", "CompanionBatch", "Companion", "EFFECT_TERMS", "effect_shape"]

#: effect terms of the companion and the shape of their parameter per batch row ([] or [3])
EFFECT_TERMS: dict[str, tuple[int, ...]] = {
    "wind": (3,),
    "linear_drag": (),
    "quadratic_drag": (),
    "table_friction": (),
    "gripper_slip": (),
    "mass_scale": (),
    "stiffness_scale": (),
}


def effect_shape(name: str) -> tuple[int, ...]:
    if name not in EFFECT_TERMS:
        raise KeyError(f"companion: no effect term {name!r} (have {', '.join(EFFECT_TERMS)})")
    return EFFECT_TERMS[name]


@dataclass
class CompanionConfig:
    """Topology, integration and nominal physical parameters (see module docstring)."""

    num_nodes: int = 96
    neighbors: int = 8  # stretch springs: nearest nodes within spring_radius_factor x spacing
    spring_radius_factor: float = 3.0
    bend_neighbors: int = 8  # bending springs: next nodes out to bend_radius_factor x spacing
    bend_radius_factor: float = 8.0
    substeps: int = 8
    iterations: int = 4  # Jacobi constraint passes per substep
    relaxation: float = 1.5  # Jacobi over-relaxation of the averaged corrections
    carry_neighbors: int = 4
    contact_offset_max: float = 0.02
    attach_radius: float = 0.02
    contact_radius: float = 0.006
    grip_threshold: float = 0.5
    # nominal physics: compliances are per unit rest length, s^2
    stretch_compliance: float = 1e-7
    bend_compliance: float = 1e-4
    grip_compliance: float = 1e-6
    drag: float = 1.0  # 1/s, still air
    friction: float = 0.5
    wind_form: str = "field"  # "field": uniform force per unit mass; "pressure": only its component along the
    # local surface normal (sheets) or across the local tangent (lines) acts, as on a real surface

    def validate(self) -> "CompanionConfig":
        if self.num_nodes < 2 or self.neighbors < 1 or self.substeps < 1 or self.carry_neighbors < 1:
            raise ValueError("CompanionConfig: num_nodes >= 2, neighbors >= 1, substeps >= 1, carry_neighbors >= 1")
        if self.iterations < 1 or not 0.0 < self.relaxation < 2.0 or self.bend_neighbors < 0:
            raise ValueError("CompanionConfig: iterations >= 1, relaxation in (0, 2), bend_neighbors >= 0")
        for name in ("spring_radius_factor", "bend_radius_factor", "attach_radius", "contact_radius", "drag",
                     "stretch_compliance", "bend_compliance", "grip_compliance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"CompanionConfig.{name} must be > 0")
        if self.wind_form not in ("field", "pressure"):
            raise ValueError(f"CompanionConfig.wind_form must be 'field' or 'pressure', got {self.wind_form!r}")
        if not 0.0 <= self.friction < 5.0 or not 0.0 < self.grip_threshold < 1.0 or self.contact_offset_max < 0:
            raise ValueError("CompanionConfig: friction in [0, 5), grip_threshold in (0, 1), contact_offset_max >= 0")
        return self


@dataclass
class CompanionBatch:
    """Constants of B episodes (or copies of episodes), made by :meth:`Companion.prepare`."""

    rest: torch.Tensor  # [B, K, 3]
    si: torch.Tensor  # [B, E] constraint ends (padded ones join node 0 to itself, weight 0)
    sj: torch.Tensor  # [B, E]
    rest_len: torch.Tensor  # [B, E]
    kind: torch.Tensor  # [B, E] 0 = padding, 1 = stretch, 2 = bending
    degree: torch.Tensor  # [B, K] constraints per node (Jacobi averaging)
    floor: torch.Tensor  # [B, K] lowest signed distance to the table plane
    carry_idx: torch.Tensor  # [B, N, k] splat skinning: nodes
    carry_w: torch.Tensor  # [B, N, k] weights (rows sum to 1)
    gravity: torch.Tensor  # [3]
    plane_normal: torch.Tensor  # [3]
    plane_offset: float
    dt: float
    sheet: bool = False  # the object is a surface (two large extents), else a line or a volume

    @property
    def size(self) -> int:
        return int(self.rest.shape[0])

    @property
    def num_nodes(self) -> int:
        return int(self.rest.shape[1])

    def repeat(self, n: int) -> "CompanionBatch":
        """The batch tiled n times (row b of copy r is row r * B + b)."""
        rep = lambda x: x.repeat((n,) + (1,) * (x.ndim - 1))  # noqa: E731
        return CompanionBatch(rep(self.rest), rep(self.si), rep(self.sj), rep(self.rest_len), rep(self.kind),
                              rep(self.degree), rep(self.floor), rep(self.carry_idx), rep(self.carry_w), self.gravity,
                              self.plane_normal, self.plane_offset, self.dt, self.sheet)


def _is_sheet(rest: torch.Tensor) -> bool:
    """Two comparable large extents and a thin third: a sheet (cloth); else a line or a volume."""
    ev = torch.linalg.eigvalsh(torch.cov(rest.t().double())).clamp_min(0).sqrt()  # ascending std
    return bool(ev[1] > 0.3 * ev[2] and ev[0] < 0.2 * ev[1])


class Companion(nn.Module):
    """Batched position-based (XPBD) spring twin with effect terms (module docstring).

    The nominal physics are parameters (log compliances, log drag, friction), so they can be
    fitted by gradient; effect parameters are passed to :meth:`rollout`, never stored here.
    """

    def __init__(self, config: Optional[CompanionConfig] = None) -> None:
        super().__init__()
        self.config = (config or CompanionConfig()).validate()
        c = self.config
        self.log_stretch = nn.Parameter(torch.tensor(math.log(c.stretch_compliance)))
        self.log_bend = nn.Parameter(torch.tensor(math.log(c.bend_compliance)))
        self.log_grip = nn.Parameter(torch.tensor(math.log(c.grip_compliance)))
        self.log_drag = nn.Parameter(torch.tensor(math.log(c.drag)))
        self.friction = nn.Parameter(torch.tensor(float(c.friction)))

    # ------------------------------------------------------------------ set-up
    @torch.no_grad()
    def prepare(self, inits: Sequence[torch.Tensor], plane_normal: torch.Tensor, plane_offset: float,
                gravity: torch.Tensor, dt: float) -> CompanionBatch:
        """Batch constants for episodes starting from splat means ``inits`` (each [N, 3], the same N)."""
        c = self.config
        if not inits:
            raise ValueError("Companion.prepare: no episodes")
        n_spl = int(inits[0].shape[0])
        if any(int(x.shape[0]) != n_spl for x in inits):
            raise ValueError("Companion.prepare: every episode must have the same number of splats")
        if n_spl < 2:
            raise ValueError(f"Companion.prepare: need >= 2 splats, got {n_spl}")
        if not (math.isfinite(float(dt)) and float(dt) > 0):
            raise ValueError(f"Companion.prepare: dt must be > 0, got {dt}")
        K = min(c.num_nodes, n_spl)
        nrm = plane_normal.detach().float().cpu()
        nrm = nrm / nrm.norm()
        off = float(plane_offset)
        rows = []
        for means in inits:
            means = means.detach().float().cpu()
            if tuple(means.shape) != (n_spl, 3) or not torch.isfinite(means).all():
                raise ValueError("Companion.prepare: splat means must be finite [N, 3]")
            rest = means[farthest_point_sampling(means, K)].clone()
            d = torch.cdist(rest, rest)
            d.fill_diagonal_(math.inf)
            spacing = max(float(d.min(dim=1).values.median()), 1e-6)
            stretch = neighbour_pairs(d, c.neighbors, c.spring_radius_factor * spacing)
            bend = neighbour_pairs(d, c.bend_neighbors, c.bend_radius_factor * spacing, skip=c.neighbors)
            if bend.numel():  # a bending pair that is also a stretch pair stays a stretch pair
                key_s = set((stretch[0] * K + stretch[1]).tolist())
                keep = torch.tensor([int(a) * K + int(b) not in key_s for a, b in bend.t()], dtype=torch.bool)
                bend = bend[:, keep]
            pairs = torch.cat([stretch, bend], dim=1)
            kind = torch.cat([torch.ones(stretch.shape[1]), 2 * torch.ones(bend.shape[1])])
            rest_len = (rest[pairs[0]] - rest[pairs[1]]).norm(dim=-1).clamp_min(1e-6)
            deg = torch.bincount(pairs.reshape(-1), minlength=K).float()
            ci, w = skin_weights(means, rest, c.carry_neighbors, spacing)
            floor = (rest @ nrm + off).clamp(min=0.0, max=c.contact_offset_max)
            rows.append((rest, pairs, rest_len, kind, deg, floor, ci, w))
        E = max(r[1].shape[1] for r in rows)
        B = len(rows)
        si = torch.zeros(B, E, dtype=torch.long)
        sj = torch.zeros(B, E, dtype=torch.long)
        rl = torch.ones(B, E)
        kd = torch.zeros(B, E)
        for b, r in enumerate(rows):
            e = r[1].shape[1]
            si[b, :e], sj[b, :e], rl[b, :e], kd[b, :e] = r[1][0], r[1][1], r[2], r[3]
        return CompanionBatch(
            rest=torch.stack([r[0] for r in rows]), si=si, sj=sj, rest_len=rl, kind=kd,
            degree=torch.stack([r[4] for r in rows]), floor=torch.stack([r[5] for r in rows]),
            carry_idx=torch.stack([r[6] for r in rows]), carry_w=torch.stack([r[7] for r in rows]),
            gravity=gravity.detach().float().cpu(), plane_normal=nrm, plane_offset=off, dt=float(dt),
            sheet=_is_sheet(rows[0][0]))

    # ------------------------------------------------------------------ dynamics
    def rollout(self, batch: CompanionBatch, control_points: torch.Tensor, gripper: torch.Tensor,
                effects: Optional[Mapping[str, torch.Tensor]] = None, frames: Optional[Sequence[int]] = None
                ) -> torch.Tensor:
        """Node positions [B, F, K, 3] at ``frames`` (default: every frame 0..T-1).

        ``control_points`` [B, T, P, 3] and ``gripper`` [B, T] (1 open): the robot at each frame
        (frame 0 only sets where it starts). ``effects``: {term: [B] or [B, 3] tensor}
        (:data:`EFFECT_TERMS`), differentiable."""
        c = self.config
        B, K = batch.size, batch.num_nodes
        if control_points.ndim != 4 or control_points.shape[0] != B or control_points.shape[-1] != 3:
            raise ValueError(f"Companion.rollout: control_points must be [{B}, T, P, 3], got {list(control_points.shape)}")
        T = int(control_points.shape[1])
        if tuple(gripper.shape) != (B, T):
            raise ValueError(f"Companion.rollout: gripper must be [{B}, {T}], got {list(gripper.shape)}")
        eff = dict(effects or {})
        for name, val in eff.items():
            want = (B,) + effect_shape(name)
            if tuple(val.shape) != want:
                raise ValueError(f"Companion.rollout: effect {name} must be {list(want)}, got {list(val.shape)}")
        keep = list(range(T)) if frames is None else sorted(set(int(f) for f in frames))
        if keep and (keep[0] < 0 or keep[-1] >= T):
            raise ValueError(f"Companion.rollout: frames must lie in [0, {T - 1}]")
        cps_all = control_points.detach().float()
        grip_all = gripper.detach().float()
        dt = batch.dt
        h = dt / c.substeps
        h2 = h * h
        # compliances per constraint (XPBD: alpha / h^2, alpha per unit rest length)
        a_str = self.log_stretch.exp() / h2
        a_bend = self.log_bend.exp() / h2
        alpha = torch.where(batch.kind == 2, a_bend, a_str) / batch.rest_len  # [B, E]
        if "stiffness_scale" in eff:
            alpha = alpha / (1.0 + eff["stiffness_scale"].clamp_min(-0.9))[:, None]
        live = (batch.kind > 0).to(alpha.dtype)
        a_grip = self.log_grip.exp() / h2
        damp = torch.exp(-self.log_drag.exp() * h)
        mu = self.friction.clamp_min(0.0).expand(B)
        if "table_friction" in eff:
            mu = (mu + eff["table_friction"]).clamp_min(0.0)
        winv = torch.ones(B)
        if "mass_scale" in eff:
            winv = 1.0 / (1.0 + eff["mass_scale"].clamp_min(-0.9))
        w_e = winv[:, None]  # [B, 1] inverse node mass (equal masses)
        ext = batch.gravity.expand(B, 1, 3)
        wind_p = None
        if "wind" in eff and c.wind_form == "pressure":
            wind_p = eff["wind"][:, None, :]
        elif "wind" in eff:
            ext = ext + eff["wind"][:, None, :]
        lin = eff["linear_drag"][:, None, None] if "linear_drag" in eff else None
        quad = eff["quadratic_drag"][:, None, None] if "quadratic_drag" in eff else None
        slip = eff["gripper_slip"].clamp_min(0.0)[:, None, None] if "gripper_slip" in eff else None
        gn = float(batch.gravity.norm())
        nrm = batch.plane_normal
        si3 = batch.si[..., None].expand(-1, -1, 3)
        sj3 = batch.sj[..., None].expand(-1, -1, 3)
        inv_deg = (c.relaxation / batch.degree.clamp_min(1.0))[..., None]  # [B, K, 1]
        x = batch.rest.clone()
        v = torch.zeros_like(x)
        held = torch.zeros(B, K, dtype=torch.bool)
        held_j = torch.zeros(B, K, dtype=torch.long)
        held_off = torch.zeros(B, K, 3)
        out = {0: x} if 0 in keep else {}
        prev = cps_all[:, 0]
        for t in range(1, (keep[-1] if keep else 0) + 1):
            cp = cps_all[:, t]  # [B, P, 3]
            closed = grip_all[:, t] < c.grip_threshold  # [B]
            xd = x.detach()
            newly = closed & ~held.any(dim=1)
            if bool(newly.any()):  # attach at closing: the nodes near the control points' centroid
                centre = cp.mean(dim=1, keepdim=True)
                near = ((xd - centre).norm(dim=-1) <= c.attach_radius) & newly[:, None]
                jn = torch.cdist(xd, cp).argmin(dim=-1)
                off = xd - torch.gather(cp, 1, jn[..., None].expand(-1, -1, 3))
                held = held | near
                held_j = torch.where(near, jn, held_j)
                held_off = torch.where(near[..., None], off, held_off)
            held = held & closed[:, None]  # opening releases
            heldf = held.to(x.dtype)[..., None]
            any_held = bool(held.any())
            f0 = gn * K / heldf.sum(dim=1, keepdim=True).clamp_min(1.0)  # [B, 1, 1] weight per held node
            for s in range(c.substeps):
                cps = prev + ((s + 1) / c.substeps) * (cp - prev)
                acc = ext
                if wind_p is not None:
                    acc = acc + self._pressure(batch, x, wind_p, si3, sj3)
                if lin is not None:
                    acc = acc - lin * v
                if quad is not None:
                    acc = acc - quad * v.norm(dim=-1, keepdim=True) * v
                v = (v + h * acc) * damp
                p = x + h * v
                for _ in range(c.iterations):
                    xi, xj = torch.gather(p, 1, si3), torch.gather(p, 1, sj3)
                    d = xj - xi
                    length = d.norm(dim=-1).clamp_min(1e-9)
                    lam = -(length - batch.rest_len) / (2.0 * w_e + alpha) * live  # [B, E]
                    corr = (lam / length)[..., None] * d  # move i along +d when stretched: -w lam n
                    dp = torch.zeros_like(p).scatter_add(1, si3, -corr).scatter_add(1, sj3, corr)
                    p = p + w_e[..., None] * dp * inv_deg
                    if any_held:
                        target = torch.gather(cps, 1, held_j[..., None].expand(-1, -1, 3)) + held_off
                        dg = (target - p) * (w_e[..., None] / (w_e[..., None] + a_grip))
                        if slip is not None:  # a saturating grip: at most f0 / s per held node
                            dg = dg / (1.0 + slip * dg.norm(dim=-1, keepdim=True) / (f0 * h2))
                        p = p + dg * heldf
                # control points push nodes out of their contact radius
                dmin, jmin = torch.cdist(p, cps).min(dim=-1)
                pen = (c.contact_radius - dmin).clamp_min(0.0)
                if bool((pen > 0).any()):
                    dirn = (p - torch.gather(cps, 1, jmin[..., None].expand(-1, -1, 3))) / dmin.clamp_min(1e-9)[..., None]
                    p = p + pen[..., None] * dirn * (1.0 - heldf)
                # table: the floor, and Coulomb friction on the tangential displacement
                depth = (batch.floor - (p @ nrm + batch.plane_offset)).clamp_min(0.0)  # [B, K]
                if bool((depth > 0).any()):
                    p = p + depth[..., None] * nrm
                    dxt = p - x
                    dxt = dxt - (dxt @ nrm)[..., None] * nrm
                    st = dxt.norm(dim=-1).clamp_min(1e-12)
                    keepf = (1.0 - mu[:, None] * depth / st).clamp_min(0.0)
                    p = p - dxt * (1.0 - keepf)[..., None] * (depth > 0).to(p.dtype)[..., None]
                v = (p - x) / h
                x = p
            prev = cp
            if t in keep:
                out[t] = x
        return torch.stack([out[t] for t in keep], dim=1)

    @staticmethod
    def _pressure(batch: CompanionBatch, x: torch.Tensor, w: torch.Tensor, si3: torch.Tensor,
                  sj3: torch.Tensor) -> torch.Tensor:
        """The part of the field w [B, 1, 3] a surface element feels: along its normal (sheet) or
        across its tangent (line); local shape from the covariance of each node's stretch edges."""
        B, K = x.shape[:2]
        d = torch.gather(x, 1, sj3) - torch.gather(x, 1, si3)
        d = d * (batch.kind == 1).to(x.dtype)[..., None]
        d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        outer = d[..., :, None] * d[..., None, :]  # [B, E, 3, 3]
        cov = torch.zeros(B, K, 9, dtype=x.dtype)
        o9 = outer.reshape(B, -1, 9)
        cov = cov.scatter_add(1, batch.si[..., None].expand(-1, -1, 9), o9).scatter_add(1, batch.sj[..., None].expand(-1, -1, 9), o9)
        cov = cov.reshape(B, K, 3, 3) + 1e-6 * torch.eye(3, dtype=x.dtype)
        evals, evecs = torch.linalg.eigh(cov)  # ascending
        if batch.sheet:
            n = evecs[..., :, 0]  # [B, K, 3] smallest: the normal
            return (w * n).sum(-1, keepdim=True) * n
        t = evecs[..., :, 2]  # largest: the tangent
        return w - (w * t).sum(-1, keepdim=True) * t

    # ------------------------------------------------------------------ splats
    @staticmethod
    def skin(batch: CompanionBatch, nodes: torch.Tensor) -> torch.Tensor:
        """Splat displacements from node displacements: nodes [B, ..., K, 3] -> [B, ..., N, 3]
        (linear blend of each splat's nearest nodes, translation only)."""
        B, K = batch.size, batch.num_nodes
        if nodes.shape[0] != B or tuple(nodes.shape[-2:]) != (K, 3):
            raise ValueError(f"Companion.skin: nodes must be [{B}, ..., {K}, 3], got {list(nodes.shape)}")
        lead = nodes.shape[1:-2]
        flat = nodes.reshape(B, -1, K, 3)  # [B, F, K, 3]
        N, kc = batch.carry_idx.shape[1:]
        idx = batch.carry_idx.reshape(B, 1, N * kc, 1).expand(-1, flat.shape[1], -1, 3)
        g = torch.gather(flat, 2, idx).reshape(B, flat.shape[1], N, kc, 3)
        out = (batch.carry_w[:, None, :, :, None] * g).sum(3)
        return out.reshape((B,) + tuple(lead) + (N, 3))
