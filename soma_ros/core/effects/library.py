"""Candidate effect terms with physical meaning, for the discrepancy workflow (issue #8).

Every term here is *zero at initialisation* (its learnable parameter starts at
0), so adding one to a trained model changes nothing until it is fitted; each
has one or two learnable scalars with a unit, and is registered in the core
registry (:func:`soma_ros.core.effects.register_effect`) so a checkpoint that
carries it loads anywhere (the package imports this module).

==================  ===========================================================
table_friction      Coulomb-like sliding friction of the table on splats within
                    ``tau`` of the plane:  F = -mu m |g_n| w(d) v_t / sqrt(|v_t|^2
                    + v_eps^2), v_t the velocity tangential to the plane, w the
                    contact weight (1 at d <= 0, smoothly 0 at d = tau), smooth
                    near v = 0 (v_eps). mu* is *signed* and unconstrained: it is
                    the friction coefficient the data asks for *in addition* to
                    what the model learned, so mu < 0 reads "the table is more
                    slippery than the model believes". [mu*, tau, v_eps]
gripper_slip        the grasp as a whole: while the gripper is closed on the object
                    (strength s = max_i (1 - c_t) w_i, w_i the smooth radial weight of
                    splat i within ``radius`` of its nearest robot control point),
                    every splat gets  F = m s (hold (u_G - v_bar) / dt + sag g),
                    u_G the grasp's velocity (the w m-weighted mean of the control
                    points' velocities), v_bar the object's mass-weighted mean
                    velocity. hold* (dimensionless, signed): the fraction of the
                    object's velocity relative to the grasp removed per step *in
                    addition* to what the model does, > 0 a tighter grip, < 0 a grip
                    that transmits less of the gripper's motion (slips); sag* (fraction
                    of g): the held object slides down out of the grasp under its load.
                    Both act on the object's mean motion (the grasp moves the object,
                    not only the splats between the fingers). With a physics prior
                    (:mod:`.physics`) these two do not act; loosen* does: > 0 the held
                    object hangs in the fingers by a critically damped spring-damper
                    of time constant 0.05 s (e^(2 loosen) - 1) (stiff at 0, lets go as it
                    grows), < 0 a tighter grip; and weaken* a friction-limited grip: the
                    fingers carry at most e^(-weaken) of the object's weight, and the
                    object slides out and falls once the part lifted off the table weighs
                    more (0: no limit). [hold*, sag*, radius, loosen*, weaken*]
mass_scale          extra weight of the lifted material: F = excess m g s(d),
                    s(d) = smoothstep((d - d0) / (d1 - d0)) = 0 on the table
                    (d <= d0, where the support carries any weight, so the rest
                    state is untouched) and 1 above d1. excess* = m_true / m_model
                    - 1 (signed: < 0 lighter). With a learned model whose
                    internal forces are fixed, a heavier object differs mainly in
                    how its unsupported parts sag; this is that handle. [excess*,
                    d0, d1]
stiffness_scale     a stiffer (> 0) or softer (< 0) material, acting only through a
                    physics prior (:mod:`.physics`); without one the elasticity lives
                    inside the learned network and the term has no handle. [log_scale*]
==================  ===========================================================

Bounds (``Effect.bounds``): mass_scale's excess in [-0.9, 9] (0.1 to 10 times the
identified mass) and stiffness_scale's log_scale in [-ln 100, ln 100]; the
discrepancy workflow keeps its fits inside them. The other terms are unbounded.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..config import ConfigError
from .base import Effect, EffectContext, _param, register_effect, smoothstep
from .mods import PhysicsMods

__all__ = ["TableFriction", "GripperSlip", "MassScale", "StiffnessScale", "smoothstep"]


@register_effect("table_friction")
class TableFriction(Effect):
    """Signed, smooth Coulomb friction of the table (module docstring)."""

    zero_at_rest = True

    @dataclass
    class Params:
        mu: float = 0.0
        tau: float = 0.015  # m: contact band above the plane
        v_eps: float = 0.02  # m/s: below this the friction fades linearly to 0 (no chatter at v = 0)

    def __init__(self, params, *, attr_dim: int = 0) -> None:
        super().__init__(params, attr_dim=attr_dim)
        if not (params.tau > 0 and params.v_eps > 0):
            raise ConfigError(f"effect table_friction: tau and v_eps must be > 0, got {params}")
        self.mu = _param(float(params.mu))

    def forward(self, ctx: EffectContext) -> torch.Tensor:
        n = ctx.plane_normal.to(ctx.positions.dtype)
        w = 1.0 - smoothstep(ctx.signed_distance() / self.params.tau)
        v = ctx.velocities
        vt = v - (v @ n)[:, None] * n[None, :]
        speed = torch.sqrt((vt * vt).sum(-1, keepdim=True) + self.params.v_eps ** 2)
        g_n = torch.clamp(-(ctx.gravity @ n), min=0.0)
        return -(self.mu * g_n) * (ctx.masses * w)[:, None] * vt / speed

    def physics_modifier(self, ctx: EffectContext):
        return PhysicsMods(friction=self.mu)


@register_effect("gripper_slip")
class GripperSlip(Effect):
    """Extra velocity coupling and sag of the grasped object as a whole (module docstring)."""

    # physics prior: loosen 0.5 / 1 / 1.5 = a grip of time constant 0.086 / 0.32 / 0.95 s, whose static sag is
    # 7 cm / 1 m / 9 m (one grid point per half decade of the grips between stiff and holding nothing)
    # weaken 0.5 / 1 / 1.5: the grip carries 61 / 37 / 22% of the object's weight
    fit_scale = {"loosen": 0.5, "weaken": 0.5}
    bounds = {"weaken": (-1.0, 10.0)}  # e^(-weaken): 0.05 to 2.7 times the object's weight
    prior_only = ("loosen", "weaken")
    force_only = ("hold", "sag")

    @dataclass
    class Params:
        hold: float = 0.0  # fraction per step
        sag: float = 0.0  # fraction of g
        radius: float = 0.03  # m
        loosen: float = 0.0  # physics prior: > 0 a compliant grip (spring-damper, tau = 0.05 s (e^(2 loosen) - 1))
        weaken: float = 0.0  # physics prior: != 0 the grip lets go once the lifted load exceeds e^(-weaken) x the weight

    def __init__(self, params, *, attr_dim: int = 0) -> None:
        super().__init__(params, attr_dim=attr_dim)
        if not params.radius > 0:
            raise ConfigError(f"effect gripper_slip: radius must be > 0, got {params.radius}")
        self.hold = _param(float(params.hold))
        self.sag = _param(float(params.sag))
        self.loosen = _param(float(params.loosen))
        self.weaken = _param(float(params.weaken))

    def physics_modifier(self, ctx: EffectContext):
        return PhysicsMods(grip=self.loosen, release=self.weaken)

    def forward(self, ctx: EffectContext) -> torch.Tensor:
        out = ctx.positions.new_zeros((ctx.num_nodes, 3))
        if ctx.control_points is None or ctx.control_points.shape[0] == 0:
            return out
        closed = (1.0 - ctx.gripper.reshape(())).clamp(0.0, 1.0)
        d2 = torch.cdist(ctx.positions.detach(), ctx.control_points.detach()) ** 2  # [N, P]
        j = d2.argmin(dim=1)
        r2 = d2.gather(1, j[:, None]).squeeze(1)
        w = closed * (1.0 - r2 / self.params.radius ** 2).clamp_min(0.0) ** 2  # [N]
        s = w.max()
        if not bool(s > 0):
            return out
        wm = w * ctx.masses
        u_g = (wm[:, None] * ctx.control_velocities[j]).sum(0) / wm.sum()  # [3] the grasp's velocity
        v_bar = (ctx.masses[:, None] * ctx.velocities).sum(0) / ctx.masses.sum().clamp_min(1e-30)  # [3]
        acc = s * (self.hold * (u_g - v_bar) / float(ctx.dt) + self.sag * ctx.gravity.to(out.dtype))  # [3]
        return ctx.masses[:, None] * acc[None, :]


@register_effect("mass_scale")
class MassScale(Effect):
    """Extra (signed) weight of the material lifted off the table (module docstring)."""

    bounds = {"excess": (-0.9, 9.0)}  # 0.1 to 10 times the identified mass

    @dataclass
    class Params:
        excess: float = 0.0
        d0: float = 0.02  # m above the plane: below, the table carries it (no force)
        d1: float = 0.05  # m: fully free from here up

    def __init__(self, params, *, attr_dim: int = 0) -> None:
        super().__init__(params, attr_dim=attr_dim)
        if not params.d1 > params.d0 >= 0:
            raise ConfigError(f"effect mass_scale: need d1 > d0 >= 0, got {params}")
        self.excess = _param(float(params.excess))

    def forward(self, ctx: EffectContext) -> torch.Tensor:
        s = smoothstep((ctx.signed_distance() - self.params.d0) / (self.params.d1 - self.params.d0))
        return (self.excess * ctx.masses * s)[:, None] * ctx.gravity.to(ctx.positions.dtype)[None, :]

    def weight_factor(self) -> torch.Tensor:
        lo, hi = self.bounds["excess"]
        return 1.0 + self.excess.clamp(lo, hi)

    def physics_modifier(self, ctx: EffectContext):
        return PhysicsMods(mass=self.excess)


@register_effect("stiffness_scale")
class StiffnessScale(Effect):
    """A stiffer (> 0) or softer (< 0) material: with a physics prior its stretch and bending
    compliances are divided by e^log_scale. Without one it has no handle (the elasticity lives
    in the network) and exerts no force."""

    fit_scale = {"log_scale": 2.0}
    prior_only = ("log_scale",)
    bounds = {"log_scale": (-math.log(100.0), math.log(100.0))}  # 1/100 to 100 times the identified stiffness

    @dataclass
    class Params:
        log_scale: float = 0.0

    def __init__(self, params, *, attr_dim: int = 0) -> None:
        super().__init__(params, attr_dim=attr_dim)
        self.log_scale = _param(float(params.log_scale))

    def forward(self, ctx: EffectContext) -> torch.Tensor:
        return ctx.positions.new_zeros(ctx.positions.shape)

    def physics_modifier(self, ctx: EffectContext):
        return PhysicsMods(stiffness=self.log_scale)
