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

from .base import (
    EFFECTS,
    Effect,
    EffectContext,
    EffectSet,
    build_effect,
    build_effects,
    known_effects,
    near_box,
    register_effect,
    smoothstep,
)
from .mods import PhysicsMods

# Registration: importing these modules registers their terms.
from . import builtin, library, physics  # noqa: E402,F401
from .builtin import Gravity, LinearDrag, QuadraticDrag, RobotForce, Support, Wind
from .library import GripperSlip, MassScale, StiffnessScale, TableFriction
from .physics import PhysicsPrior

__all__ = [
    "EFFECTS",
    "Effect",
    "EffectContext",
    "EffectSet",
    "PhysicsMods",
    "build_effect",
    "build_effects",
    "known_effects",
    "near_box",
    "register_effect",
    "smoothstep",
    "Gravity",
    "Support",
    "RobotForce",
    "Wind",
    "LinearDrag",
    "QuadraticDrag",
    "TableFriction",
    "GripperSlip",
    "MassScale",
    "StiffnessScale",
    "PhysicsPrior",
]
