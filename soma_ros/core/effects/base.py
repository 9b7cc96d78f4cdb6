"""The effect machinery: :class:`EffectContext`, :class:`Effect`, the registry
(:func:`register_effect`) and :class:`EffectSet` (see :mod:`soma_ros.core.effects`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable, ClassVar, Iterable, Optional, Sequence, Union

import torch
from torch import nn

from ..config import ConfigError, EffectSpec, from_dict
from .mods import PhysicsMods

__all__ = [
    "EffectContext",
    "Effect",
    "EFFECTS",
    "register_effect",
    "build_effect",
    "build_effects",
    "EffectSet",
    "known_effects",
    "near_box",
    "smoothstep",
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
    #: (the discrepancy workflow's Adam steps, :func:`soma_ros.discrepancy.workflow.fit_effect`)
    fit_scale: ClassVar[dict[str, float]] = {}
    #: a physics prior (:mod:`.physics`): the other terms act through it (``physics_modifier``)
    hosts_modifiers: ClassVar[bool] = False
    #: physical range (lo, hi) of a learnable parameter's every element, where one exists (absent:
    #: unbounded). A fitter keeps its values inside (:func:`soma_ros.discrepancy.workflow.fit_effect`): a value
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
        otherwise (:class:`~.library.MassScale`, as a 0-dim tensor differentiable in its
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


def near_box(points: torch.Tensor, x: torch.Tensor, r: float) -> torch.Tensor:
    """Indices [C] of the rows of ``x`` [N, 3] inside the bounding box of ``points`` [P, 3]
    grown by ``r``: a cheap prefilter for "within r of any of the points" (a superset)."""
    lo = points.min(0).values - r
    hi = points.max(0).values + r
    return torch.nonzero(((x >= lo) & (x <= hi)).all(-1)).squeeze(-1)
