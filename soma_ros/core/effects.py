"""Force terms ("effects") acting on the splats, in a registry.

Each effect is an ``nn.Module`` registered by name with
:func:`register_effect`; a model config lists its effects by name with
parameters (:class:`soma_ros.core.config.EffectSpec`) and
:func:`build_effects` turns the list into an :class:`EffectSet`. New effects
are config-addable: adding ``{name: wind}`` to a trained model adds a zero
force whose parameters can then be fitted alone (the discrepancy workflow).

Contract: ``effect(ctx: EffectContext) -> Tensor[N, 3]``, the force in newtons
on each of the N splats (the finest level). The simulator sums the forces of
all effects per splat and aggregates them bottom-up through the hierarchy as
**sums per cluster** (Newton: the net external force on a cluster is the sum
over its members); the network then sees each node's force per unit mass,
F_cluster / m_cluster, i.e. the mass-weighted mean of its members'
accelerations.

``in_reference``: effects that define the static equilibrium of the initial
state (gravity and support). The simulator evaluates the network once at the
initial state under these forces only and subtracts that response from every
step (see :mod:`.simulator`); all other effects (robot, wind, drag) act as
deviations from it.

``direct`` (per instance, ``EffectSpec.direct``, default False): the term's
force is *also* integrated by the simulator as an explicit acceleration on top
of the network's (residual physics), not only fed to the network as a
feature. A network trained without, say, wind has never learned what a wind
feature means and barely responds to it; a direct term moves the object by
construction (uniform wind: rigid translation 1/2 a t^2). The reference
effects cannot be direct (their response is learned and subtracted at rest;
integrating them too would count gravity twice): :func:`build_effect` raises.

Built-in effects (parameters in brackets, * = learnable):

==================  ===========================================================
gravity             m g, g from the scene [scale]
support             m w(d) (gain* max(0, -g.n) + k* max(0, -d)) n: within tau of
                    the table plane (signed distance d < tau) a support that
                    carries the splat's weight (gain 1 cancels gravity's normal
                    part at contact), plus a penalty k (1/s^2) on penetration;
                    w = 1 at d <= 0 falling smoothly to 0 at d = tau [tau, gain*,
                    stiffness*]
robot               graph module: edges from each robot control point to its
                    ``max_neighbors`` nearest splats within ``radius`` (kNN
                    filtered by radius, like the level graphs; the cap bounds
                    the cost on dense objects: 30 points x 64 <= 1,920 edges,
                    where a 5 cm ball can hold thousands of splats); edge
                    features = relative position,
                    distance, gripper state c_t, control-point velocity, relative
                    velocity, splat attributes; messages (smoothly cut off at the
                    radius) summed per splat and decoded to a force. Exactly zero
                    for splats with no control point in range [radius,
                    max_neighbors, hidden*, layers]. ``form: coupling``: the
                    same edges with a physical structure instead (velocity
                    coupling k (v_cp - v) / dt, k in (0, 1), plus a push/pull
                    along finger -> splat; only rotation-invariant scalar
                    coefficients learned; :class:`RobotForce`) [prior_grip,
                    prior_open]
wind                acceleration field m a g(t), a learnable, zero-init; g ramps from 0 to 1
                    at onset (s since the rollout's start, fixed; default 0: from the start) [accel*]
linear_drag         -b m v [coeff*]
quadratic_drag      -c m |v| v [coeff*]
==================  ===========================================================
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable, ClassVar, Iterable, Optional, Sequence, Union

import torch
from torch import nn

from .config import ConfigError, EffectSpec, from_dict

__all__ = [
    "EffectContext",
    "Effect",
    "EFFECTS",
    "register_effect",
    "build_effect",
    "build_effects",
    "EffectSet",
    "known_effects",
]


# ----------------------------------------------------------------------------- context
@dataclass
class EffectContext:
    """What an effect may look at, on the splat level (N splats, P control points).

    =====================  =========  =================================================
    field                  shape      meaning
    =====================  =========  =================================================
    positions              [N, 3]     splat positions x_t, m
    velocities             [N, 3]     (x_t - x_{t-1}) / dt, m/s
    masses                 [N]        kg
    attrs                  [N, A]     learned per-splat attributes
    gravity                [3]        m/s^2
    plane_normal           [3]        unit normal of the table plane, pointing to the
                                      object side (against gravity)
    plane_offset           []         d of the plane n.x + d = 0 (signed distance n.x+d)
    dt                     float      step, s
    control_points         [P, 3]     robot control points at t (or None: no robot)
    control_velocities     [P, 3]     their velocities, m/s (or None)
    gripper                []         gripper state c_t in [0, 1] (or None)
    rest_positions         [N, 3]     the episode's initial splat positions (or None)
    cache                  dict       per-episode constants an effect builds once (or None)
    state_in / state_out   dict       what effects carried over from the previous step / carry
                                      to the next one (``SimState.aux``), by effect key (or None)
    physics_mods           -          :class:`~.physics.PhysicsMods` the other terms ask of a
                                      physics prior (set by :class:`EffectSet`; or None)
    time                   float      s since the rollout's initial state (steps x dt; the live
                                      node: since its reset), for terms that switch on mid-episode
    =====================  =========  =================================================
    """

    positions: torch.Tensor
    velocities: torch.Tensor
    masses: torch.Tensor
    attrs: torch.Tensor
    gravity: torch.Tensor
    plane_normal: torch.Tensor
    plane_offset: torch.Tensor
    dt: float
    control_points: Optional[torch.Tensor] = None
    control_velocities: Optional[torch.Tensor] = None
    gripper: Optional[torch.Tensor] = None
    rest_positions: Optional[torch.Tensor] = None
    cache: Optional[dict] = None
    physics_mods: Optional[object] = None
    time: float = 0.0
    state_in: Optional[dict] = None
    state_out: Optional[dict] = None

    def __post_init__(self) -> None:
        n = self.positions.shape[0]
        if self.positions.ndim != 2 or self.positions.shape[1] != 3:
            raise ValueError(f"EffectContext.positions must be [N, 3], got {list(self.positions.shape)}")
        if tuple(self.velocities.shape) != (n, 3) or tuple(self.masses.shape) != (n,):
            raise ValueError("EffectContext: velocities must be [N, 3] and masses [N]")
        if self.attrs.ndim != 2 or self.attrs.shape[0] != n:
            raise ValueError(f"EffectContext.attrs must be [N, A], got {list(self.attrs.shape)}")
        if tuple(self.gravity.shape) != (3,) or tuple(self.plane_normal.shape) != (3,):
            raise ValueError("EffectContext: gravity and plane_normal must be [3]")
        if self.control_points is not None:
            if self.control_points.ndim != 2 or self.control_points.shape[1] != 3:
                raise ValueError(f"EffectContext.control_points must be [P, 3], got {list(self.control_points.shape)}")
            if self.control_velocities is None or self.control_velocities.shape != self.control_points.shape:
                raise ValueError("EffectContext.control_velocities must be [P, 3] with control_points")
            if self.gripper is None or self.gripper.numel() != 1:
                raise ValueError("EffectContext.gripper must be a scalar tensor with control_points")
        if self.rest_positions is not None and tuple(self.rest_positions.shape) != (n, 3):
            raise ValueError(f"EffectContext.rest_positions must be [{n}, 3], got {list(self.rest_positions.shape)}")

    @property
    def num_nodes(self) -> int:
        return int(self.positions.shape[0])

    def signed_distance(self) -> torch.Tensor:
        """[N] signed distance to the table plane (> 0 on the object side), m."""
        return self.positions @ self.plane_normal + self.plane_offset


# ----------------------------------------------------------------------------- registry
EFFECTS: dict[str, type["Effect"]] = {}


def register_effect(name: str) -> Callable[[type["Effect"]], type["Effect"]]:
    """Class decorator: register an :class:`Effect` subclass under ``name``."""

    def deco(cls: type["Effect"]) -> type["Effect"]:
        if not (isinstance(cls, type) and issubclass(cls, Effect)):
            raise TypeError(f"register_effect({name!r}): {cls!r} is not an Effect subclass")
        if name in EFFECTS and EFFECTS[name] is not cls:
            raise ValueError(f"register_effect: an effect named {name!r} is already registered")
        if not dataclasses.is_dataclass(cls.Params):
            raise TypeError(f"register_effect({name!r}): {cls.__name__}.Params must be a dataclass")
        cls.name = name
        EFFECTS[name] = cls
        return cls

    return deco


def known_effects() -> list[str]:
    return sorted(EFFECTS)


class Effect(nn.Module):
    """Base class. Subclasses define ``Params`` (a dataclass) and ``forward(ctx) -> [N, 3]``."""

    name: ClassVar[str] = ""
    in_reference: ClassVar[bool] = False
    #: the force is exactly zero whenever every splat is at rest (velocity-dependent terms):
    #: frames before the robot reaches the object stay exact no-ops (the trainer skips them)
    zero_at_rest: ClassVar[bool] = False
    #: typical magnitude of each learnable parameter, in its unit (absent: 1): a fitter that
    #: steps every parameter by a learning rate times this covers a comparable range of force
    #: (the discrepancy workflow's Adam steps, :func:`trainer.discrepancy.fit_effect`)
    fit_scale: ClassVar[dict[str, float]] = {}
    #: a physics prior (:mod:`.physics`): the other terms act through it (``physics_modifier``)
    hosts_modifiers: ClassVar[bool] = False
    #: physical range (lo, hi) of a learnable parameter's every element, where one exists (absent:
    #: unbounded). A fitter keeps its values inside (:func:`trainer.discrepancy.fit_effect`): a value
    #: outside describes another object, not this one with an effect (a rope 10^4 times softer
    #: is a string). Only properties of the object identified by the model have one (mass,
    #: stiffness: within two orders of magnitude, or one for mass, of the identified value); fields,
    #: drags and the grip do not (a wind can be any strength, a grip can let go entirely).
    bounds: ClassVar[dict[str, tuple[float, float]]] = {}

    @dataclass
    class Params:
        pass

    def __init__(self, params, *, attr_dim: int = 0) -> None:
        super().__init__()
        self.params = params
        self.attr_dim = int(attr_dim)

    def forward(self, ctx: EffectContext) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def physics_modifier(self, ctx: EffectContext):
        """What this term changes in a physics prior (:class:`~.physics.PhysicsMods`), or None: a
        term with a physical meaning there (wind, drag, friction, grip, mass, stiffness) acts
        through the prior instead of as a force of its own when the model has one."""
        return None

    def robot_reach(self) -> Optional[float]:
        """How close (m) a robot control point must come for this term to act on the object,
        or None for a term the robot does not drive."""
        return None

    def weight_factor(self) -> "float | torch.Tensor":
        """How many times its identified weight the object has with this term (1: unchanged). A
        force sensor at the wrist feels it; only a term that changes the object's mass says
        otherwise (:class:`~.effects_library.MassScale`, as a 0-dim tensor differentiable in its
        parameter)."""
        return 1.0

    #: parameters that act only through a physics prior, and those that act only as the term's own
    #: force (without one): the discrepancy workflow fits the ones that act in the model at hand
    prior_only: ClassVar[tuple[str, ...]] = ()
    force_only: ClassVar[tuple[str, ...]] = ()

    def acting_parameters(self, through_prior: bool) -> list[tuple[str, nn.Parameter]]:
        """(name, parameter) of the learnable parameters that change this term's action, acting
        through a physics prior (``through_prior``) or as a force of its own."""
        skip = self.force_only if through_prior else self.prior_only
        return [(n, p) for n, p in self.named_parameters() if n not in skip]

    def project_(self) -> list[str]:
        """Clamp every bounded parameter into :attr:`bounds` in place (no autograd record);
        returns the names of those that were outside or sit on a bound."""
        at: list[str] = []
        with torch.no_grad():
            for n, (lo, hi) in self.bounds.items():
                p = getattr(self, n)
                p.clamp_(min=lo, max=hi)
                if bool(((p <= lo) | (p >= hi)).any()):
                    at.append(n)
        return at

    def extra_repr(self) -> str:
        return ", ".join(f"{f.name}={getattr(self.params, f.name)!r}" for f in dataclasses.fields(self.params))


def build_effect(spec: Union[EffectSpec, str, dict], attr_dim: int = 0) -> Effect:
    """One effect from its spec; unknown names/params raise :class:`ConfigError` listing the known ones."""
    spec = EffectSpec.parse(spec)
    cls = EFFECTS.get(spec.name)
    if cls is None:
        raise ConfigError(f"unknown effect {spec.name!r}; known effects: {', '.join(known_effects())}")
    if spec.direct and cls.in_reference:
        raise ConfigError(
            f"effect {spec.instance_key}: a reference effect ({spec.name}) cannot be direct: its response is "
            "learned by the network and subtracted at rest; integrating it explicitly too would count it twice"
        )
    params = from_dict(cls.Params, spec.params, f"effect {spec.instance_key}: ")
    eff = cls(params, attr_dim=attr_dim)
    if not spec.trainable:
        eff.requires_grad_(False)
    return eff


class EffectSet(nn.Module):
    """An ordered set of effect instances (keyed by ``EffectSpec.instance_key``)."""

    def __init__(self, specs: Iterable[Union[EffectSpec, str, dict]] = (), attr_dim: int = 0) -> None:
        super().__init__()
        self.attr_dim = int(attr_dim)
        self.terms = nn.ModuleDict()
        self._specs: dict[str, EffectSpec] = {}
        for s in specs:
            self.add(s)

    def add(self, spec: Union[EffectSpec, str, dict]) -> Effect:
        spec = EffectSpec.parse(spec)
        key = spec.instance_key
        if key in self.terms:
            raise ConfigError(f"effect key {key!r} is already present (present: {', '.join(self.terms)})")
        eff = build_effect(spec, self.attr_dim)
        self.terms[key] = eff
        self._specs[key] = dataclasses.replace(spec, params=dict(spec.params))
        return eff

    def remove(self, key: str) -> None:
        if key not in self.terms:
            raise KeyError(f"no effect {key!r} (present: {', '.join(self.terms)})")
        del self.terms[key]
        del self._specs[key]

    @property
    def specs(self) -> list[EffectSpec]:
        return [self._specs[k] for k in self.terms]

    def keys(self) -> list[str]:
        return list(self.terms.keys())

    def __getitem__(self, key: str) -> Effect:
        return self.terms[key]

    def __contains__(self, key: str) -> bool:
        return key in self.terms

    @property
    def physics_host(self) -> Optional[str]:
        """Key of the physics prior (an effect with ``hosts_modifiers``), or None."""
        return next((k for k, e in self.terms.items() if e.hosts_modifiers), None)

    def weight_factor(self, as_tensor: bool = False) -> "float | torch.Tensor":
        """The product of the terms' :meth:`Effect.weight_factor`: the object's weight over its identified
        one; with ``as_tensor`` as the terms give it (a 0-dim tensor differentiable in their parameters
        where one is, else the float 1.0)."""
        f = 1.0
        for e in self.terms.values():
            f = f * e.weight_factor()
        return f if as_tensor else float(f.detach() if isinstance(f, torch.Tensor) else f)

    def robot_reach(self) -> Optional[float]:
        """The largest reach of the terms the robot drives (``Effect.robot_reach``), or None."""
        reach = [r for r in (e.robot_reach() for e in self.terms.values()) if r is not None]
        return max(reach) if reach else None

    def _with_modifiers(self, ctx: EffectContext) -> tuple[EffectContext, set]:
        """With a physics prior: the context carrying what the other terms change in it, and the
        keys of those terms (they act through the prior, not as forces of their own)."""
        if self.physics_host is None:
            return ctx, set()
        from .physics import PhysicsMods

        mods, keys = PhysicsMods(), set()
        for key, eff in self.terms.items():
            m = None if eff.hosts_modifiers else eff.physics_modifier(ctx)
            if m is not None:
                mods, keys = mods.add(m), keys | {key}
        return dataclasses.replace(ctx, physics_mods=mods), keys

    def forward(self, ctx: EffectContext, reference_only: bool = False) -> torch.Tensor:
        """Total force [N, 3] (newtons); ``reference_only`` sums the in-reference effects only."""
        total = ctx.positions.new_zeros((ctx.num_nodes, 3))
        ctx, through = self._with_modifiers(ctx) if not reference_only else (ctx, set())
        for key, eff in self.terms.items():
            if (reference_only and not eff.in_reference) or key in through:
                continue
            f = eff(ctx)
            if tuple(f.shape) != (ctx.num_nodes, 3):
                raise RuntimeError(f"effect {key!r} returned shape {list(f.shape)}, expected [{ctx.num_nodes}, 3]")
            total = total + f
        return total

    @property
    def direct_keys(self) -> list[str]:
        """Keys of the direct effects (``EffectSpec.direct``), in order."""
        return [k for k in self.terms if self._specs[k].direct]

    def split(self, ctx: EffectContext) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
        """(force the network sees [N, 3], force of the direct effects alone [N, 3] or None when
        there are none), each effect evaluated once. The first is every effect but those with
        ``feature: false``; with none of those it equals :meth:`forward` bit for bit."""
        total, direct, _ = self.split_active(ctx, check_active=False)
        return total, direct

    def split_active(self, ctx: EffectContext, check_active: bool = True, exempt: Sequence[str] = ()
                     ) -> tuple[torch.Tensor, Optional[torch.Tensor], int]:
        """:meth:`split` plus which non-reference forces act (exert a force on any splat):
        0 = none (only gravity and the support: the object is untouched), 1 = only ``direct``
        ones, 2 = one that is not ``direct``. Below 2 the network's output is the object's
        response to gravity, the support and the motion the direct effects cause, to no other
        force (the passive-object rule of :mod:`.simulator` applies). A term whose key is in
        ``exempt`` counts as not direct here (``DynamicsConfig.passive_exempt``). Always 2 when
        ``check_active`` is False, which skips the check and its device synchronisations."""
        total = ctx.positions.new_zeros((ctx.num_nodes, 3))
        direct = None
        level = 0 if check_active else 2
        ctx, through = self._with_modifiers(ctx)
        for key, eff in self.terms.items():
            if key in through:  # acts through the physics prior
                continue
            f = eff(ctx)
            if tuple(f.shape) != (ctx.num_nodes, 3):
                raise RuntimeError(f"effect {key!r} returned shape {list(f.shape)}, expected [{ctx.num_nodes}, 3]")
            spec = self._specs[key]
            as_direct = spec.direct and key not in exempt
            if level < 2 and not eff.in_reference and (level < 1 or not as_direct) and bool((f != 0).any()):
                level = 1 if as_direct else 2
            if spec.feature:
                total = total + f
            if spec.direct:
                direct = f if direct is None else direct + f
        return total, direct, level

    def per_term(self, ctx: EffectContext) -> dict[str, torch.Tensor]:
        """Force [N, 3] of every effect, by key (a term acting through a physics prior: zeros)."""
        ctx, through = self._with_modifiers(ctx)
        return {k: (ctx.positions.new_zeros((ctx.num_nodes, 3)) if k in through else e(ctx))
                for k, e in self.terms.items()}


def build_effects(specs: Iterable[Union[EffectSpec, str, dict]], attr_dim: int = 0) -> EffectSet:
    """An :class:`EffectSet` from names / mappings / :class:`EffectSpec` s."""
    return EffectSet(specs, attr_dim=attr_dim)


def smoothstep(t: torch.Tensor) -> torch.Tensor:
    """C1 step: 0 for t <= 0, 1 for t >= 1, 3t^2 - 2t^3 in between."""
    t = t.clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _param(value, dtype=torch.float32) -> nn.Parameter:
    return nn.Parameter(torch.as_tensor(value, dtype=dtype).clone())


# ----------------------------------------------------------------------------- built-in effects
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


def near_box(points: torch.Tensor, x: torch.Tensor, r: float) -> torch.Tensor:
    """Indices [C] of the rows of ``x`` [N, 3] inside the bounding box of ``points`` [P, 3]
    grown by ``r``: a cheap prefilter for "within r of any of the points" (a superset)."""
    lo = points.min(0).values - r
    hi = points.max(0).values + r
    return torch.nonzero(((x >= lo) & (x <= hi)).all(-1)).squeeze(-1)


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
    resting object all along. The discrepancy workflow does not fit it (docs/discrepancy.md,
    session 33: set by hand at a gust's true onset, it did not halve that gust's gap)."""

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
        from .physics import PhysicsMods

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
        from .physics import PhysicsMods

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
        from .physics import PhysicsMods

        return PhysicsMods(quadratic_drag=self.coeff)


from . import effects_library  # noqa: E402,F401
from . import physics  # noqa: E402,F401
