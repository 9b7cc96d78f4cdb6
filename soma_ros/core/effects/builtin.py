"""The built-in effect terms: gravity, support, robot, wind, linear and quadratic drag
(documented in :mod:`soma_ros.core.effects`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable, ClassVar, Iterable, Optional, Sequence, Union

import torch
from torch import nn

from ..config import ConfigError
from .base import Effect, EffectContext, _param, near_box, register_effect, smoothstep
from .mods import PhysicsMods


@register_effect("gravity")
class Gravity(Effect):
    """m g on every splat (g from the scene)."""

    in_reference = True

    @dataclass
    class Params:
        scale: float = 1.0

    def forward(self, ctx: EffectContext) -> torch.Tensor:
        return ctx.masses[:, None] * (self.params.scale * ctx.gravity)[None, :]


@register_effect("support")
class Support(Effect):
    """Table support within ``tau`` of the plane (see module docstring).

    Penalty form with a learned magnitude: ``gain`` scales the weight-carrying
    part (1 = cancels the normal component of gravity at contact), the
    penetration stiffness k (1/s^2, learned in log space) pushes splats below
    the plane back out. w(d) = 1 - smoothstep(d / tau) for d in [0, tau].
    """

    in_reference = True

    @dataclass
    class Params:
        tau: float = 0.01
        gain: float = 1.0
        stiffness: float = 500.0

    def __init__(self, params, *, attr_dim: int = 0) -> None:
        super().__init__(params, attr_dim=attr_dim)
        if not params.tau > 0 or not params.stiffness > 0:
            raise ConfigError(f"effect support: tau and stiffness must be > 0, got {params}")
        self.gain = _param(float(params.gain))
        self.log_stiffness = _param(float(torch.log(torch.tensor(params.stiffness))))

    def forward(self, ctx: EffectContext) -> torch.Tensor:
        n = ctx.plane_normal
        d = ctx.signed_distance()
        t = (d / self.params.tau).clamp(0.0, 1.0)
        w = 1.0 - t * t * (3.0 - 2.0 * t)  # 1 at d <= 0, 0 at d >= tau, C1 in between
        weight_n = torch.clamp(-(ctx.gravity @ n), min=0.0)  # |normal part of g| when it pushes into the table
        mag = self.gain * weight_n + self.log_stiffness.exp() * torch.relu(-d)
        return (ctx.masses * w * mag)[:, None] * n[None, :]


@register_effect("robot")
class RobotForce(Effect):
    """Robot-induced force from the control points to the splats in reach.

    ``form: mlp`` (default): a small message-passing module; edge messages from free
    features (relative position and velocities in the world frame, gripper state) decoded
    to a force. It can represent any force, including one with no physical cause (a
    closed, motionless gripper pushing the object up).

    ``form: coupling``: the same edges, but the force has a physical structure; only
    scalar coefficients are learned, from rotation-invariant edge features
    (distance / radius, gripper state, relative speed, approach speed, splat attributes):

        a_i = sum_j w_ij [ k_ij (v_j - v_i) / dt + b_ij u_ij ] / max(1, sum_j w_ij)

    with w_ij the smooth cutoff (1 at the control point, 0 at the radius), k_ij in (0, 1)
    the fraction of the velocity difference to control point j removed per step (grip,
    friction, pushing: dissipative, unconditionally stable under the simulator's
    semi-implicit step), b_ij in (-accel_scale, accel_scale) m/s^2 a push (> 0) or pull
    along u_ij, the unit vector from control point j to splat i. So a control point at rest
    relative to a splat exerts no force but b u, which points from the finger to the
    splat: a motionless closed gripper cannot lift the object, and the force has no
    preferred world direction. The learned logit of k is added to a prior that goes from
    logit(``prior_open``) with the gripper open to logit(``prior_grip``) closed.

    ``carry`` (form coupling; 0 = off): the grasp carries the object. A splat's grasp
    weight is omega_i = min(1, sum_j w_ij) (1 - c) with c the gripper state (1 open); the
    grasp moves at u_G, the omega m-weighted mean over the splats of their control points'
    (w-weighted) velocity; the object moves at v_bar, its mass-weighted mean velocity. Every
    splat gets the fraction (1 - omega_i) of

        A = phi s (u_G - v_bar) / dt,    a'_i = a_i + (1 - omega_i) A,

    with s = max_i omega_i the grasp's strength and phi in (0, 1) a learned fraction that
    starts at ``carry``. So with a closed gripper the rest of the object follows the grasped
    part (the tension of a rope or cloth that a gripper lifts or drags), which the per-splat
    coupling alone leaves to the network, while the grasped splats keep their own a_i. Like
    k it is dissipative: it removes a fraction of the object's velocity relative to the grasp
    each step (never more), so a motionless closed gripper brings the object to rest, not
    into a drift. With the gripper open or nothing in reach it is exactly zero.
    """

    FEATURES = 11  # + attr_dim (form mlp)
    COUPLING_FEATURES = 4  # + attr_dim (form coupling)
    FORMS = ("mlp", "coupling")

    @dataclass
    class Params:
        radius: float = 0.05
        max_neighbors: int = 64  # per control point; 0 = every splat within the radius
        hidden: int = 32
        layers: int = 1
        accel_scale: float = 9.81
        velocity_scale: float = 1.0
        form: str = "mlp"
        prior_grip: float = 0.25  # form coupling: initial k with the gripper closed (fraction of dv per step)
        prior_open: Optional[float] = None  # form coupling: initial k with the gripper open (None: prior_grip)
        carry: float = 0.0  # form coupling: initial fraction phi of the velocity relative to the grasp removed per step (0 = off)

    def __init__(self, params, *, attr_dim: int = 0) -> None:
        super().__init__(params, attr_dim=attr_dim)
        if not params.radius > 0 or params.hidden < 1 or params.layers < 0 or params.max_neighbors < 0:
            raise ConfigError(
                f"effect robot: radius > 0, max_neighbors >= 0, hidden >= 1, layers >= 0 required, got {params}"
            )
        if params.form not in self.FORMS:
            raise ConfigError(f"effect robot: form must be one of {', '.join(self.FORMS)}, got {params.form!r}")
        for name in ("prior_grip", "prior_open"):
            v = getattr(params, name)
            if v is not None and not 0.0 < v < 1.0:
                raise ConfigError(f"effect robot: {name} must be in (0, 1), got {v}")
        if not 0.0 <= params.carry < 1.0 or (params.carry > 0 and params.form != "coupling"):
            raise ConfigError(f"effect robot: carry must be in [0, 1) and needs form coupling, got {params.carry}")
        h = params.hidden
        if params.form == "coupling":
            layers = [nn.Linear(self.COUPLING_FEATURES + attr_dim, h), nn.SiLU()]
            for _ in range(params.layers):
                layers += [nn.Linear(h, h), nn.SiLU()]
            head = nn.Linear(h, 2)
            with torch.no_grad():  # start near the prior: k = prior (closed..open by the gripper state), b = 0
                head.weight.mul_(0.1)
                head.bias.zero_()
            self.coef_mlp = nn.Sequential(*layers, head)
            logit = lambda q: math.log(q / (1.0 - q))  # noqa: E731
            k_open = params.prior_grip if params.prior_open is None else params.prior_open
            self._logit_closed = logit(params.prior_grip)
            self._logit_open = logit(k_open)
            if params.carry > 0:
                self.carry_logit = nn.Parameter(torch.tensor(logit(params.carry)))
            return
        fin = self.FEATURES + attr_dim
        edge = [nn.Linear(fin, h), nn.SiLU()]
        for _ in range(params.layers):
            edge += [nn.Linear(h, h), nn.SiLU()]
        self.edge_mlp = nn.Sequential(*edge[:-1])  # no activation on the message
        node = [nn.Linear(h, h), nn.SiLU()]
        for _ in range(params.layers - 1):
            node += [nn.Linear(h, h), nn.SiLU()]
        node.append(nn.Linear(h, 3, bias=False))  # a bias would cancel in node_mlp(agg) - node_mlp(0)
        self.node_mlp = nn.Sequential(*node)

    def robot_reach(self) -> Optional[float]:
        return float(self.params.radius)

    def edges(self, ctx: EffectContext) -> tuple[torch.Tensor, torch.Tensor]:
        """(control-point index [E], splat index [E]): each control point's nearest
        ``max_neighbors`` splats closer than the radius."""
        cp = ctx.control_points.detach()
        r = self.params.radius
        x = ctx.positions.detach()
        cand = near_box(cp, x, r)
        if cand.numel() == 0:
            z = torch.zeros(0, dtype=torch.long, device=x.device)
            return z, z
        d2 = ((x[cand][None, :, :] - cp[:, None, :]) ** 2).sum(-1)  # [P, C]
        k = self.params.max_neighbors
        if k and cand.numel() > k:
            d2k, ck = torch.topk(d2, k, dim=1, largest=False, sorted=False)  # [P, k]
            j, slot = torch.nonzero(d2k < r * r, as_tuple=True)
            return j, cand[ck[j, slot]]
        j, c = torch.nonzero(d2 < r * r, as_tuple=True)
        return j, cand[c]

    def forward(self, ctx: EffectContext) -> torch.Tensor:
        n = ctx.num_nodes
        out = ctx.positions.new_zeros((n, 3))
        if ctx.control_points is None or ctx.control_points.shape[0] == 0:
            return out
        j, i = self.edges(ctx)
        if i.numel() == 0:
            return out
        p = self.params
        rel = ctx.positions[i] - ctx.control_points[j]  # [E, 3], differentiable
        dist = torch.sqrt((rel * rel).sum(-1, keepdim=True) + 1e-18)
        cpv = ctx.control_velocities[j]
        if p.form == "coupling":
            return self._coupling(ctx, i, j, rel, dist, cpv, out)
        feats = [
            rel / p.radius,
            dist / p.radius,
            ctx.gripper.reshape(1, 1).expand(rel.shape[0], 1).to(rel.dtype),
            cpv / p.velocity_scale,
            (ctx.velocities[i] - cpv) / p.velocity_scale,
        ]
        if self.attr_dim:
            feats.append(ctx.attrs[i])
        f = torch.cat(feats, dim=-1)
        cut = (1.0 - (dist / p.radius) ** 2).clamp_min(0.0) ** 2  # smooth cutoff: 0 at the radius
        msg = cut * self.edge_mlp(f)
        active = torch.nonzero(torch.bincount(i, minlength=n)).squeeze(-1)  # sorted splats in reach
        slot = torch.full((n,), -1, dtype=torch.long, device=i.device)
        slot[active] = torch.arange(active.shape[0], device=i.device)
        inv = slot[i]
        agg = msg.new_zeros((active.shape[0], msg.shape[1])).index_add_(0, inv, msg)
        acc = self.node_mlp(agg) - self.node_mlp(agg.new_zeros((1, agg.shape[1])))  # 0 when no message
        force = (ctx.masses[active] * p.accel_scale)[:, None] * acc
        return out.index_copy(0, active, force)

    def _coupling(self, ctx: EffectContext, i: torch.Tensor, j: torch.Tensor, rel: torch.Tensor,
                  dist: torch.Tensor, cpv: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        """Form ``coupling`` (class docstring): [E] edges -> force [N, 3] on the splats."""
        p = self.params
        u = rel / dist  # [E, 3] unit, control point -> splat
        dv = cpv - ctx.velocities[i]  # [E, 3] velocity of the control point relative to the splat
        feats = [
            dist / p.radius,
            ctx.gripper.reshape(1, 1).expand(rel.shape[0], 1).to(rel.dtype),
            torch.sqrt((dv * dv).sum(-1, keepdim=True) + 1e-18) / p.velocity_scale,
            -(u * dv).sum(-1, keepdim=True) / p.velocity_scale,  # > 0: the control point approaches
        ]
        if self.attr_dim:
            feats.append(ctx.attrs[i])
        coef = self.coef_mlp(torch.cat(feats, dim=-1))  # [E, 2]
        g = feats[1]  # [E, 1] gripper state: 1 open, 0 closed
        prior = self._logit_open * g + self._logit_closed * (1.0 - g)
        k = torch.sigmoid(coef[:, :1] + prior)
        b = p.accel_scale * torch.tanh(coef[:, 1:])
        w = (1.0 - (dist / p.radius) ** 2).clamp_min(0.0) ** 2  # [E, 1] smooth cutoff
        acc_e = w * (k * dv / float(ctx.dt) + b * u)  # [E, 3] m/s^2
        acc = out.index_add(0, i, acc_e)
        wsum = out.new_zeros((out.shape[0],)).index_add_(0, i, w[:, 0])
        acc = acc / wsum.clamp_min(1.0)[:, None]
        if p.carry > 0:
            omega = wsum.clamp_max(1.0) * (1.0 - ctx.gripper.reshape(()).to(acc.dtype))  # [N] grasp weight
            wm = omega * ctx.masses
            cpv_i = out.index_add(0, i, w * cpv) / wsum.clamp_min(1e-30)[:, None]  # [N, 3] control points' velocity
            u_g = (wm[:, None] * cpv_i).sum(0) / wm.sum().clamp_min(1e-30)  # [3] the grasp's velocity
            v_bar = (ctx.masses[:, None] * ctx.velocities).sum(0) / ctx.masses.sum().clamp_min(1e-30)  # [3]
            a_carry = torch.sigmoid(self.carry_logit) * omega.max() * (u_g - v_bar) / float(ctx.dt)
            acc = acc + (1.0 - omega)[:, None] * a_carry
        return ctx.masses[:, None] * acc


@register_effect("wind")
class Wind(Effect):
    """Constant acceleration field (m/s^2) times mass; learnable, zero by default.

    In a model with a physics prior (:mod:`.physics`) the field acts inside it; ``form``
    ``pressure`` (default) lets only its component across a line's tangent or along a sheet's
    normal act, as moving air presses on a rope or a cloth (a cloth lying flat in a horizontal
    wind feels nothing), ``field`` all of it. Without a prior the field acts on every splat.

    ``onset`` (s since the rollout's start, :attr:`EffectContext.time`; a fixed setting, >= 0): the
    field is fully on from then and ramps in over the ``rise`` seconds before it (C1 smoothstep); 0
    (default) blows from the first step. A fan switched on, a door opened, a gust: a disturbance
    that starts during the episode, which a field from the start could only imitate by pushing the
    resting object all along. The discrepancy workflow does not fit it: set by hand at a gust's
    true onset, it did not halve that gust's gap (docs/design_decisions.md)."""

    fit_scale = {"accel": 9.81}  # m/s^2: a force field comparable to the object's weight
    FORMS = ("pressure", "field")

    @dataclass
    class Params:
        accel: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
        form: str = "pressure"
        onset: float = 0.0  # s
        rise: float = 0.1   # s, fixed

    def __init__(self, params, *, attr_dim: int = 0) -> None:
        super().__init__(params, attr_dim=attr_dim)
        if len(params.accel) != 3:
            raise ConfigError(f"effect wind: accel must have 3 entries, got {params.accel}")
        if params.form not in self.FORMS:
            raise ConfigError(f"effect wind: form must be one of {', '.join(self.FORMS)}, got {params.form!r}")
        if not (math.isfinite(float(params.onset)) and float(params.onset) >= 0.0):
            raise ConfigError(f"effect wind: onset must be a time >= 0 s, got {params.onset}")
        if not (math.isfinite(float(params.rise)) and float(params.rise) > 0.0):
            raise ConfigError(f"effect wind: rise must be > 0 s, got {params.rise}")
        self.accel = _param(list(params.accel))

    def gate(self, ctx: EffectContext) -> torch.Tensor:
        """[] in [0, 1]: how much of the field blows at ``ctx.time`` (1 from ``onset`` on)."""
        u = (float(ctx.time) - float(self.params.onset)) / float(self.params.rise) + 1.0
        return smoothstep(self.accel.new_tensor(u))

    def accel_at(self, ctx: EffectContext) -> torch.Tensor:
        """[3] the field at ``ctx.time``, m/s^2."""
        return self.accel.to(ctx.positions.dtype) * self.gate(ctx)

    def forward(self, ctx: EffectContext) -> torch.Tensor:
        return ctx.masses[:, None] * self.accel_at(ctx)[None, :]

    def physics_modifier(self, ctx: EffectContext):
        a = self.accel_at(ctx)
        return PhysicsMods(pressure=a) if self.params.form == "pressure" else PhysicsMods(accel=a)


@register_effect("linear_drag")
class LinearDrag(Effect):
    """-b m v (b in 1/s, learnable, unconstrained so a fit can report its sign)."""

    zero_at_rest = True

    @dataclass
    class Params:
        coeff: float = 0.0

    def __init__(self, params, *, attr_dim: int = 0) -> None:
        super().__init__(params, attr_dim=attr_dim)
        self.coeff = _param(float(params.coeff))

    def forward(self, ctx: EffectContext) -> torch.Tensor:
        return -(self.coeff * ctx.masses)[:, None] * ctx.velocities

    def physics_modifier(self, ctx: EffectContext):
        return PhysicsMods(linear_drag=self.coeff)


@register_effect("quadratic_drag")
class QuadraticDrag(Effect):
    """-c m |v| v (c in 1/m, learnable)."""

    zero_at_rest = True
    fit_scale = {"coeff": 5.0}  # 1/m: c |v| ~ 1/s at a tabletop speed of 0.2 m/s

    @dataclass
    class Params:
        coeff: float = 0.0

    def __init__(self, params, *, attr_dim: int = 0) -> None:
        super().__init__(params, attr_dim=attr_dim)
        self.coeff = _param(float(params.coeff))

    def forward(self, ctx: EffectContext) -> torch.Tensor:
        v = ctx.velocities
        speed = torch.sqrt((v * v).sum(-1, keepdim=True) + 1e-18)
        return -(self.coeff * ctx.masses)[:, None] * speed * v

    def physics_modifier(self, ctx: EffectContext):
        return PhysicsMods(quadratic_drag=self.coeff)


