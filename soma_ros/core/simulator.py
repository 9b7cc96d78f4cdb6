"""The SoMA simulator step: G_t = phi(G_{t-1}, G_{t-2}, R_t), pure torch.

Levels are those of the :class:`~.hierarchy.Hierarchy`: 0 = splats, 1..L-1
= clusters, L = root. One step, given the state at t (and t-1) and the robot
action R_t in the simulation frame:

1. **Forces** (:mod:`.effects`) on every splat, summed per cluster up the
   hierarchy; node feature = force per mass F/m of the node.
2. **Top-down**, level L down to 1, the shared GNN (:mod:`.gnn`) runs on the
   level's graph (static + dynamic edges) and predicts per node an
   acceleration a and a deformation (U, V, log s). A node k with anchor p
   (its parent; the root's anchor is the world) moves as

       c_k'  = x_p' + Fbar_p' (X_k - X_p)        position the anchor carries it to
       d_k'  = d_k + dt * clamp(v_k + dt * a_k)   residual offset, v_k = (d_k - d_k^-) / dt
       x_k'  = c_k' + clamp(d_k')

   with X the rest positions, Fbar the node's effective deformation
   ``Fbar_k' = F_k Fbar_p'`` (product down from the root, as in the paper's
   prod_j F^j), ``F_k = U diag(s) V^T R_k`` and the node's accumulated rotation
   ``R_k' = U V^T R_k``. So U diag(s) V^T is the per-step update: U V^T the
   rotation increment, V diag(s) V^T a symmetric stretch (volume preserving:
   log s normalised to sum 0, so prod s = 1), and F_k is always an exact
   rotation times a bounded stretch (det F = 1).
3. **Splats** are carried by their fine cluster: x = c (plus a residual
   from the per-splat head if ``gnn.splat_head``), Sigma' = Fbar Sigma_rest
   Fbar^T, rotation q' = Rbar q_rest with Rbar the product of the accumulated
   rotations (exact for the covariance; the quaternion ignores the stretch).

Node features: anchor acceleration (second difference of c), F/m, velocity
relative to the anchor (v_k above), learned attributes (mean of the
splats'); edge features: see :mod:`.graph`.

Direct effects (residual physics)
---------------------------------
Every force enters the network as the F/m feature above; that is the only
pathway of the learned dynamics, so a term the network was never trained with
(wind on a model trained under gravity + support + robot) moves the object
only as much as the network happens to respond to an unfamiliar feature. An
effect marked ``direct`` (``EffectSpec.direct``) is *also* integrated
explicitly: with a_k = F_direct,k / m_k the direct force per mass of node k
(forces summed up the hierarchy as above), the root adds a_root and every
lower simulated level adds only its excess over its anchor,
a_k - a_parent(k), to the network's acceleration in the residual update

    d_k' = d_k + dt * clamp(v_k + dt * (a_k^net + a_k^direct))

(same clamps). The anchor already carries a node by its parent's motion, so
nothing is counted twice: uniform direct wind translates the object rigidly
(a network whose outputs do not change: d_root after n steps from rest =
a dt^2 n (n + 1) / 2, semi-implicit Euler; -> 1/2 a (n dt)^2), and a force on
some splats moves their clusters relative to the rest. The splat level gets
its excess only where the network runs on it (``gnn.splat_head``); otherwise splats follow their fine cluster, which only translates and turns
as the network says: a direct term that bends the object within a fine cluster (the physics
prior's rod) is realised only as far as the clusters' translations follow it. Reference effects (gravity, support) cannot be direct
(their response is the learned one, subtracted at rest). With no direct effect
the step is the network-only step, bit for bit; a direct effect whose force is zero adds exact zeros (same positions). A direct effect with
``feature: false`` is left out of the F/m feature: pure physics the network does not
see, so it responds only to the motion the term causes (the default ``tiny`` training
config runs the robot coupling this way: with the force also as a feature, the network
learned "robot force -> upward acceleration" from lift episodes and drove the rope up
while a closed gripper lowered it, a feedback loop that ran to the speed bound).

Passive object (``DynamicsConfig.passive_friction``, off unless set)
----------------------------------------------------------------
The root carries the object's translation and is the one unbounded level. On a step
where every force other than gravity and the support is zero or direct, the network's
root update may slow the root down and make it fall, but not raise its horizontal or
upward speed; resting on the table, Coulomb friction brakes its horizontal speed
(:meth:`Simulator._passive_root`). When nothing holds the object up (no force at all but
gravity and the support, or only direct ones with the gripper open: an open gripper's
coupling drags, it does not carry), a rising root slows down at least as under gravity,
and so do the lower levels' motions relative to their anchors. Zero motion stays exactly
zero (the rest fixed point below is kept bit for bit).

At rest stays at rest (structural)
----------------------------------
The initial state of an episode is taken to be in static equilibrium under
the *reference* effects (gravity + support: the object was reconstructed
lying on the table). ``init_state`` runs the network once on that state,
exactly as a step at rest would (same features, graph, latents), and stores
its outputs; every step subtracts them. A step from a state identical to the
initial one with no other force therefore outputs exactly 0, hence a = 0,
U = V = identity, s = 1, F = I, and every carry, residual and deformation is
recomputed bit-for-bit: the object does not move, whatever the weights (a
random network included). Anything that changes the inputs -- the robot
within reach, wind, a changed support -- produces motion. Consequences: a
newly added effect (e.g. ``wind``) acts from the first step; an object
initialised in mid-air would stay there until disturbed under the default
``reference="initial"``; pass ``reference="force_free"`` to use a force-free
reference instead (gravity then acts from the start).

Bounds (``DynamicsConfig``): |v_k| <= max_speed (residual velocity), |log s|
<= 2 max_log_stretch, |d_k| <= residual_factor x the rest radius of the
anchor's cluster (not for the root, which carries the object's translation).
So after T steps the root has moved at most T dt max_speed and every node
lies within a fixed distance of the root (see :meth:`Simulator.extent_bound`).
The clamps are identities inside their bounds (no effect on normal motion).

The exact fixed point needs deterministic kernels: true on CPU; on CUDA
``index_add_`` uses atomics, so call ``torch.use_deterministic_algorithms(True)``
for bitwise rest and reproducible rollouts there.

Where the compute goes: the network runs on the cluster levels only (at 13k
splats ~1,400 fine clusters for a cloth, ~70 for the rope) unless
``gnn.splat_head``; the splat level costs a gather and two 3x3 products per
splat (carry and covariance) plus the effects. See :mod:`.gnn` for the
message-passing layout.

Turned network frame (training augmentation)
--------------------------------------------
Table-top physics is the same under a turn about gravity, but the network reads and
writes world-frame vectors, so from a handful of episodes it can learn direction-specific
responses that do not carry to an object lying another way. ``init_state(...,
network_yaw=theta)`` makes an episode whose network sees the world turned by theta about
gravity (the table normal when gravity is zero): its vector inputs (anchor acceleration,
F/m, relative velocity; the edge directions and relative velocities) are turned by Q, its
acceleration output is turned back by Q^T and its deformation update D' = U' S V'^T by
D = Q^T D' Q (computed as I + Q^T (D' - I) Q, so that no update stays exactly none). The
physical terms, the bounds and the rest fixed point are untouched (the reference pass
runs in the same frame). theta = 0 (the default, and every rollout outside training) is
the world frame, bit for bit.

Differentiable end to end (``rollout`` under autograd); graph indices are
constants. Call ``init_state`` again after the parameters change (each
training rollout): the reference is computed with the weights of that moment
(or :meth:`Simulator.refresh_reference` on a kept state).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Optional, Sequence, Union

import torch
from torch import nn

from .config import EffectSpec, ModelConfig
from .effects import Effect, EffectContext, EffectSet
from .geometry import quat_conjugate, quat_multiply, quat_normalize, quat_to_rotmat, rotmat_to_quat, sym3_eigh
from .gnn import HEAD_OUTPUTS, HierarchicalGNN, MessageGraph, Normalizer, node_feature_size
from .graph import EDGE_FEATURES, LevelGraphs, build_static_graphs, dynamic_edges, edge_features, safe_norm
from .hierarchy import Hierarchy, build_hierarchy
from .splats import Splats

__all__ = ["SceneContext", "RobotAction", "Episode", "SimState", "Simulator", "SimulationDiverged"]

_REFERENCE_MODES = ("initial", "force_free")


class SimulationDiverged(FloatingPointError):
    """A step produced non-finite positions: the model, or a term added to it, is unstable (e.g. a
    negative drag that feeds energy in). Raised by :meth:`Simulator.step` so that no NaN reaches a
    caller's neighbour search, renderer or published message."""


# ----------------------------------------------------------------------------- inputs
@dataclass
class SceneContext:
    """The environment of an episode, in the simulation frame.

    gravity [3] m/s^2; table plane ``{x : n.x + d = 0}`` with unit normal
    ``plane_normal`` [3] pointing to the object's side (against gravity) and
    ``plane_offset`` d (m), so the signed distance of x is n.x + d; dt in s.
    """

    gravity: torch.Tensor
    plane_normal: torch.Tensor
    plane_offset: Union[float, torch.Tensor]
    dt: float

    def __post_init__(self) -> None:
        g = torch.as_tensor(self.gravity, dtype=torch.float32) if not isinstance(self.gravity, torch.Tensor) else self.gravity
        n = torch.as_tensor(self.plane_normal, dtype=torch.float32) if not isinstance(self.plane_normal, torch.Tensor) else self.plane_normal
        if tuple(g.shape) != (3,) or tuple(n.shape) != (3,):
            raise ValueError(f"SceneContext: gravity and plane_normal must be [3], got {list(g.shape)}, {list(n.shape)}")
        if not (torch.isfinite(g).all() and torch.isfinite(n).all()):
            raise ValueError("SceneContext: gravity and plane_normal must be finite")
        nn_ = float(n.norm())
        if nn_ < 1e-6:
            raise ValueError("SceneContext: plane_normal has zero length")
        n = n / nn_
        if float(g @ n) > 1e-6 * max(float(g.norm()), 1.0):
            raise ValueError(
                f"SceneContext: plane_normal {n.tolist()} points along gravity {g.tolist()}; it must point to the "
                "object's side of the table (n . g <= 0)"
            )
        d = torch.as_tensor(self.plane_offset, dtype=n.dtype, device=n.device).reshape(())
        if not torch.isfinite(d):
            raise ValueError("SceneContext: plane_offset must be finite")
        if not (math.isfinite(float(self.dt)) and float(self.dt) > 0):
            raise ValueError(f"SceneContext: dt must be > 0, got {self.dt}")
        self.gravity, self.plane_normal, self.plane_offset, self.dt = g, n, d, float(self.dt)

    @staticmethod
    def table(height: float = 0.0, g: float = 9.81, dt: float = 1.0 / 30.0) -> "SceneContext":
        """z-up scene: table z = height, gravity (0, 0, -g)."""
        return SceneContext(torch.tensor([0.0, 0.0, -g]), torch.tensor([0.0, 0.0, 1.0]), -height, dt)

    def to(self, device=None, dtype=None) -> "SceneContext":
        return SceneContext(
            self.gravity.to(device=device, dtype=dtype),
            self.plane_normal.to(device=device, dtype=dtype),
            self.plane_offset.to(device=device, dtype=dtype),
            self.dt,
        )


@dataclass
class RobotAction:
    """Robot action R_t in the simulation frame: control points [P, 3] (m) and the
    gripper state c_t in [0, 1] (float or one-element tensor)."""

    control_points: torch.Tensor
    gripper: Union[float, torch.Tensor] = 0.0

    def __post_init__(self) -> None:
        cp = self.control_points
        if not isinstance(cp, torch.Tensor):
            cp = torch.as_tensor(cp, dtype=torch.float32)
        if cp.ndim != 2 or cp.shape[1] != 3:
            raise ValueError(f"RobotAction.control_points must be [P, 3], got {list(cp.shape)}")
        if not torch.isfinite(cp).all():
            raise ValueError("RobotAction.control_points must be finite")
        g = self.gripper
        g = g.reshape(()) if isinstance(g, torch.Tensor) and g.numel() == 1 else g
        if isinstance(g, torch.Tensor) and g.ndim != 0:
            raise ValueError(f"RobotAction.gripper must be a scalar or [1], got {list(g.shape)}")
        gv = float(g)
        if not (0.0 <= gv <= 1.0):
            raise ValueError(f"RobotAction.gripper must lie in [0, 1], got {gv}")
        self.control_points = cp
        self.gripper = g if isinstance(g, torch.Tensor) else torch.tensor(gv, dtype=cp.dtype, device=cp.device)

    @property
    def is_open(self) -> bool:
        """Gripper state >= 0.5: an open gripper's coupling drags, it does not carry (the passive rule)."""
        return float(self.gripper) >= 0.5


# ----------------------------------------------------------------------------- state
@dataclass
class Episode:
    """Constants of one rollout, made by :meth:`Simulator.init_state` (shared by its states).

    Per level l (lists of length L + 1): ``rest`` [N_l, 3] rest positions of
    this episode's initial splats, ``masses`` [N_l], ``attrs`` [N_l, A],
    ``offsets`` [N_l, 3] = X_l - X_parent (None at the root),
    ``residual_limit`` [N_l] (None at the root), ``reference`` [N_l, 14]
    network outputs at the initial state (None where no network runs),
    ``static_rest_vectors`` [E_l, 3] rest vectors of the static edges.
    ``network_frame``: Q [3, 3], the turn the network sees the world in, or None.
    Splat constants: ``rest_covs`` [N0, 3, 3], ``rest_quats`` [N0, 4].
    """

    scene: SceneContext
    rest: list[torch.Tensor]
    masses: list[torch.Tensor]
    attrs: list[torch.Tensor]
    offsets: list[Optional[torch.Tensor]]
    residual_limit: list[Optional[torch.Tensor]]
    rest_covs: torch.Tensor
    rest_quats: torch.Tensor
    reference_mode: str = "initial"
    reference: list[Optional[torch.Tensor]] = field(default_factory=list)
    static_rest_vectors: list[Optional[torch.Tensor]] = field(default_factory=list)
    #: constants an effect builds once per episode (``EffectContext.cache``; e.g. the physics
    #: prior's nodes and constraints), shared by every state of the rollout
    cache: dict = field(default_factory=dict)
    #: the network's frame (see "Turned network frame"): Q [3, 3], None = the world frame
    network_frame: Optional[torch.Tensor] = None


@dataclass
class SimState:
    """Simulator state at step t (lists are per level, 0 = splats ... L = root).

    ``positions`` / ``prev_positions`` [N_l, 3]: x_t, x_{t-1}.
    ``carry`` / ``carry_prev`` [N_l, 3]: where the anchor carries each node (c_t, c_{t-1}).
    ``resid`` / ``resid_prev`` [N_l, 3]: residual offsets d = x - c.
    ``rot`` [N_l, 4]: accumulated rotation (w, x, y, z) of each node's deformation
    (None where no network runs). ``deform`` [N_l, 3, 3]: effective deformation Fbar
    (None on the splat level without a splat head).
    Splats: ``means`` [N0, 3], ``covs`` [N0, 3, 3], ``quats`` [N0, 4].
    ``control_points`` [P, 3]: the last action's (for control-point velocities).
    ``dyn_edges`` / ``dyn_step``: cached dynamic edges per level and the step they were built at.
    """

    step: int
    positions: list[torch.Tensor]
    prev_positions: list[torch.Tensor]
    carry: list[torch.Tensor]
    carry_prev: list[torch.Tensor]
    resid: list[torch.Tensor]
    resid_prev: list[torch.Tensor]
    rot: list[Optional[torch.Tensor]]
    deform: list[Optional[torch.Tensor]]
    means: torch.Tensor
    covs: torch.Tensor
    quats: torch.Tensor
    episode: Episode
    control_points: Optional[torch.Tensor] = None
    dyn_edges: list[Optional[torch.Tensor]] = field(default_factory=list)
    dyn_step: list[int] = field(default_factory=list)
    #: what effects carry from one step to the next, by effect key (``EffectContext.state_in`` /
    #: ``state_out``; e.g. the physics prior's grasp: which nodes the fingers hold, at which offsets)
    aux: dict = field(default_factory=dict)
    #: the network's contribution to the step that made this state (scalar, differentiable): the mean
    #: over the levels it runs on of the mean over their nodes of |output - at-rest output|^2 (the 14
    #: head numbers: the residual acceleration in units of ``dynamics.accel_scale``, the deformation's
    #: raw quaternion and log-scale numbers; 0 = the physical terms alone). None: no network ran
    network_sq: Optional[torch.Tensor] = None

    @property
    def num_levels(self) -> int:
        return len(self.positions)

    @property
    def velocities(self) -> list[torch.Tensor]:
        """Per-level velocities (x_t - x_{t-1}) / dt [N_l, 3]."""
        dt = self.episode.scene.dt
        return [(x - xp) / dt for x, xp in zip(self.positions, self.prev_positions)]

    def detach(self) -> "SimState":
        """Same state cut from the autograd graph (truncated backprop); episode constants
        (including the reference outputs) detached too -- see :meth:`Simulator.refresh_reference`."""

        def d(v):
            if isinstance(v, torch.Tensor):
                return v.detach()
            if isinstance(v, (list, tuple)):
                return type(v)(d(x) for x in v)
            if isinstance(v, dict):
                return {k: d(x) for k, x in v.items()}
            return v

        ep = self.episode
        ep2 = dataclasses.replace(
            ep,
            rest=d(ep.rest), masses=d(ep.masses), attrs=d(ep.attrs), offsets=d(ep.offsets),
            residual_limit=d(ep.residual_limit), rest_covs=ep.rest_covs.detach(),
            rest_quats=ep.rest_quats.detach(), reference=d(ep.reference),
            static_rest_vectors=d(ep.static_rest_vectors),
        )
        kw = {f.name: d(getattr(self, f.name)) for f in dataclasses.fields(self) if f.name != "episode"}
        return SimState(episode=ep2, **kw)

    def to_splats(self, template: Splats) -> Splats:
        """Splats at this state (:func:`splats_from_covariances`, started from the state's rotations)."""
        return splats_from_covariances(self.means, self.covs, template, rotations=self.quats)


# ----------------------------------------------------------------------------- helpers
def splats_from_covariances(means: torch.Tensor, covs: torch.Tensor, template: Splats,
                            rotations: Optional[torch.Tensor] = None) -> Splats:
    """Splats with these means [N, 3] and covariances [N, 3, 3] exactly (quats / scales from an
    eigen-decomposition, :func:`~soma_ros.core.geometry.sym3_eigh`); colours, opacities, mass and
    attrs from ``template``. ``rotations`` [N, 4] (w, x, y, z), optional: the splats' accumulated
    rotations, where the Jacobi sweeps start (the covariance is F Sigma F^T with F mostly a
    rotation); the result is the same decomposition either way."""
    if len(template) != means.shape[0]:
        raise ValueError(f"to_splats: template has {len(template)} splats, state {means.shape[0]}")
    init = quat_to_rotmat(quat_normalize(rotations.detach().double())) if rotations is not None else None
    evals, evecs = sym3_eigh(covs.double(), init=init)
    quats = rotmat_to_quat(evecs).to(means.dtype)
    scales = evals.clamp_min(1e-20).sqrt().to(means.dtype)
    t = template.to(device=means.device)
    return Splats(
        means=means.detach(), quats=quats, scales=scales, opacities=t.opacities, sh_dc=t.sh_dc,
        sh_rest=t.sh_rest, mass=t.mass, attrs=t.attrs,
    )


def _clamp_norm(v: torch.Tensor, limit: Union[float, torch.Tensor]) -> torch.Tensor:
    """Scale rows of v [N, 3] down to norm <= limit (float or [N]); identity inside the bound."""
    n = safe_norm(v, keepdim=True)
    lim = limit if not isinstance(limit, torch.Tensor) else limit[:, None]
    return v * torch.clamp(lim / n, max=1.0)


def _no_gain(v_old: torch.Tensor, v_net: torch.Tensor, up: torch.Tensor, g_dt: float, untouched: bool) -> torch.Tensor:
    """Velocities [N, 3] ``v_net`` limited so that, per row, the speed perpendicular to ``up``
    does not exceed ``v_old``'s (direction kept) and the speed along ``up`` does not exceed
    max(``v_old``'s, 0) -- max(``v_old``'s - ``g_dt``, 0) when ``untouched`` (a rising body
    slows down at least as under gravity). Slowing down and falling pass unchanged; equal
    inputs at rest give exactly 0. The passive-object rule's first part (Simulator._passive_root)."""
    vu0 = (v_old * up).sum(-1, keepdim=True)
    vu1 = (v_net * up).sum(-1, keepdim=True)
    vh0, vh1 = v_old - vu0 * up, v_net - vu1 * up
    s0, s1 = vh0.norm(dim=-1, keepdim=True), vh1.norm(dim=-1, keepdim=True)
    vh1 = vh1 * torch.where(s1 > s0, s0 / s1.clamp_min(1e-30), torch.ones_like(s1))
    up_cap = (vu0 - g_dt if untouched else vu0).clamp_min(0.0)
    return vh1 + torch.minimum(vu1, up_cap) * up


def _quat_from_raw(o: torch.Tensor) -> torch.Tensor:
    """[N, 4] raw head numbers -> unit quaternion; 0 -> identity. w >= 0.5 before normalising, so never 0."""
    w = 1.0 + 0.5 * torch.tanh(o[:, :1])
    return quat_normalize(torch.cat([w, torch.tanh(o[:, 1:])], dim=-1))


def _gather_matvec(F: torch.Tensor, idx: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """F[idx] @ v per row: F [M, 3, 3], idx [N], v [N, 3] -> [N, 3]."""
    return (F.index_select(0, idx) * v[:, None, :]).sum(-1)


def network_turn(scene: SceneContext, yaw: float) -> Optional[torch.Tensor]:
    """Q [3, 3]: the turn by ``yaw`` rad about the scene's up axis (against gravity; the table
    normal when gravity is zero); None for 0."""
    yaw = float(yaw)
    if not math.isfinite(yaw):
        raise ValueError(f"network_yaw must be finite, got {yaw}")
    if yaw == 0.0:
        return None
    g = scene.gravity
    up = -g / g.norm() if float(g.norm()) > 1e-9 else scene.plane_normal
    half = 0.5 * yaw
    q = torch.cat([up.new_tensor([math.cos(half)]), math.sin(half) * up])
    return quat_to_rotmat(q[None])[0]


class Simulator(nn.Module):
    """Learned hierarchical GS simulator (see module docstring).

    Usage::

        sim = Simulator(load_model_config("cpu", object="rope"))
        state = sim.init_state(splats, SceneContext.table(dt=1/30))   # builds the hierarchy once
        state = sim.step(state, RobotAction(control_points, gripper=1.0))
        states = sim.rollout(state, actions)

    The hierarchy is built on the first ``init_state`` (or :meth:`bind`) and
    kept: the model is per object. ``init_state`` with splats of the same
    count reuses it (the rest shape of the new episode is taken from those
    splats); a different count raises.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = copy.deepcopy(config).validate()
        cfg = self.config
        self.gnn = HierarchicalGNN(cfg.gnn)
        self.effects = EffectSet(cfg.effects, attr_dim=cfg.gnn.attr_dim)
        nl = cfg.num_levels
        nf = node_feature_size(cfg.gnn.attr_dim)
        fit = cfg.normalizer.mode == "fit"
        self.node_norms = nn.ModuleList(
            Normalizer(nf, fit, cfg.normalizer.max_count, cfg.normalizer.eps) for _ in range(nl)
        )
        self.edge_norms = nn.ModuleList(
            Normalizer(EDGE_FEATURES, fit, cfg.normalizer.max_count, cfg.normalizer.eps) for _ in range(nl)
        )
        self.hierarchy: Optional[Hierarchy] = None
        self.graphs: Optional[LevelGraphs] = None
        self.splat_attrs: Optional[nn.Parameter] = None
        #: False: the network's contribution is switched off (:meth:`set_network`)
        self.network_enabled = True

    # ------------------------------------------------------------------ binding
    @property
    def device(self) -> torch.device:
        return next(self.gnn.parameters()).device

    @property
    def dtype(self) -> torch.dtype:
        return next(self.gnn.parameters()).dtype

    @property
    def is_bound(self) -> bool:
        return self.hierarchy is not None

    @property
    def num_levels(self) -> int:
        return self.config.num_levels

    @property
    def sim_levels(self) -> list[int]:
        """Levels the network runs on, top-down (root first; splats last with a splat head)."""
        top = self.num_levels - 1
        levels = list(range(top, 0, -1))
        return levels + [0] if self.config.gnn.splat_head else levels

    def bind(
        self,
        splats: Splats,
        hierarchy: Optional[Hierarchy] = None,
        graphs: Optional[LevelGraphs] = None,
    ) -> Hierarchy:
        """Build (or adopt) the hierarchy and static graphs for ``splats``; creates the
        per-splat attribute parameter [N, attr_dim] (from ``splats.attrs`` when it has that
        width, else zeros). Rebuild the optimiser after binding: it adds a parameter."""
        cfg = self.config
        if hierarchy is None:
            hierarchy = build_hierarchy(
                splats.means.detach().cpu().float(), splats.mass.detach().cpu().float(),
                cfg.hierarchy.thresholds, cfg.hierarchy.seed_fraction,
            )
        if hierarchy.sizes[0] != len(splats):
            raise ValueError(f"bind: hierarchy is for {hierarchy.sizes[0]} splats, got {len(splats)}")
        a = cfg.gnn.attr_dim
        attrs = None
        if splats.attrs is not None and tuple(splats.attrs.shape) == (len(splats), a):
            attrs = splats.attrs.detach().clone()
        return self.bind_hierarchy(hierarchy, graphs, attrs)

    def bind_hierarchy(
        self,
        hierarchy: Hierarchy,
        graphs: Optional[LevelGraphs] = None,
        attrs: Optional[torch.Tensor] = None,
    ) -> Hierarchy:
        """Adopt a hierarchy (e.g. from a checkpoint); static graphs are built if not given;
        per-splat attributes [N0, attr_dim] start from ``attrs`` (default zeros)."""
        cfg = self.config
        if hierarchy.num_levels != cfg.num_levels:
            raise ValueError(
                f"bind: hierarchy has {hierarchy.num_levels} levels, the model config {cfg.num_levels}"
            )
        if graphs is None:
            graphs = build_static_graphs(
                hierarchy.rest_positions, cfg.graph.k, cfg.graph.radii, backend=cfg.graph.knn_backend
            )
        if graphs.sizes != hierarchy.sizes:
            raise ValueError(f"bind: graphs are for level sizes {graphs.sizes}, hierarchy has {hierarchy.sizes}")
        n0, a = hierarchy.sizes[0], cfg.gnn.attr_dim
        if attrs is None:
            attrs = torch.zeros(n0, a)
        if tuple(attrs.shape) != (n0, a):
            raise ValueError(f"bind: attrs must be [{n0}, {a}], got {list(attrs.shape)}")
        self.hierarchy = hierarchy.to(self.device, self.dtype)
        self.graphs = graphs.to(self.device)
        self.splat_attrs = nn.Parameter(attrs.detach().to(self.device, self.dtype).clone())
        return self.hierarchy

    def _apply(self, fn, recurse=True):  # move the bound hierarchy with .to()/.cuda()/.double()
        super()._apply(fn, recurse)
        if self.hierarchy is not None:
            h = self.hierarchy
            self.hierarchy = Hierarchy(
                thresholds=list(h.thresholds), parents=[fn(p) for p in h.parents],
                rest_positions=[fn(x) for x in h.rest_positions], masses=[fn(m) for m in h.masses],
                seed_fraction=h.seed_fraction,
            )
            self.graphs = LevelGraphs([fn(e) for e in self.graphs.static], list(self.graphs.sizes))
        return self

    # ------------------------------------------------------------------ effects
    def add_effect(self, spec: Union[EffectSpec, str, dict]) -> Effect:
        """Add a force term by spec (e.g. ``{"name": "wind"}``); it is saved with the model."""
        eff = self.effects.add(spec)
        eff.to(device=self.device, dtype=self.dtype)
        self.config.effects = self.effects.specs
        return eff

    def acting_parameters(self, key: str) -> list[tuple[str, nn.Parameter]]:
        """(name, parameter) of effect ``key`` that act in this model: through its physics prior if it
        has one (``EffectSet.physics_host``), else as the term's own force (``Effect.acting_parameters``)."""
        eff = self.effects[key]
        through = self.effects.physics_host is not None and not eff.hosts_modifiers
        return eff.acting_parameters(through)

    def effect_parameters(self, key: str) -> list[nn.Parameter]:
        """Trainable parameters of one effect (to fit it alone)."""
        return [p for p in self.effects[key].parameters() if p.requires_grad]

    def set_normalizer_fitting(self, on: bool) -> None:
        """Switch accumulation of the feature normalisers on/off (active in training mode)."""
        for m in list(self.node_norms) + list(self.edge_norms):
            m.fit = bool(on)

    # ------------------------------------------------------------------ init
    def init_state(self, splats: Splats, scene: SceneContext, reference: str = "initial",
                   network_yaw: float = 0.0) -> SimState:
        """Initial state (at rest: x_{-1} = x_0) of an episode starting from ``splats``.

        ``reference``: "initial" (the initial state is the static equilibrium under gravity and
        support: it stays put until disturbed) or "force_free" (see module docstring).
        ``network_yaw`` (rad): the network sees the world turned by this angle about gravity
        (module docstring, "Turned network frame"; a training augmentation); 0 = world frame.
        """
        if reference not in _REFERENCE_MODES:
            raise ValueError(f"init_state: reference must be one of {_REFERENCE_MODES}, got {reference!r}")
        if not self.is_bound:
            self.bind(splats)
        h = self.hierarchy
        if len(splats) != h.sizes[0]:
            raise ValueError(
                f"init_state: the model is bound to {h.sizes[0]} splats, got {len(splats)} (one model per object)"
            )
        dev, dt_ = self.device, self.dtype
        sp = splats.to(device=dev, dtype=dt_)
        scene = scene.to(device=dev, dtype=dt_)
        L = h.root_level
        rest, masses = h.aggregate_positions(sp.means, sp.mass)
        attrs = h.aggregate_mean(self.splat_attrs)
        offsets: list[Optional[torch.Tensor]] = []
        limits: list[Optional[torch.Tensor]] = []
        for l, off in enumerate(h.offsets(rest)):
            p = h.parents[l]
            radius = torch.zeros(h.sizes[l + 1], dtype=dt_, device=dev).scatter_reduce(
                0, p, off.norm(dim=-1), reduce="amax", include_self=True
            )
            offsets.append(off)
            limits.append(self.config.dynamics.residual_factor * radius.index_select(0, p).clamp_min(1e-4))
        offsets.append(None)
        limits.append(None)
        ep = Episode(
            scene=scene, rest=rest, masses=masses, attrs=attrs, offsets=offsets, residual_limit=limits,
            rest_covs=sp.covariances(), rest_quats=quat_normalize(sp.quats), reference_mode=reference,
            static_rest_vectors=[
                rest[l].index_select(0, e[0]) - rest[l].index_select(0, e[1]) for l, e in enumerate(self.graphs.static)
            ],
            network_frame=network_turn(scene, network_yaw),
        )
        state = self._rest_state(ep)
        ep.reference, state.dyn_edges = self._reference_pass(state)
        return state

    def refresh_reference(self, state: SimState) -> SimState:
        """The same state with its episode's reference outputs (and aggregated attributes)
        recomputed under the current weights, differentiably.

        ``init_state`` computes the reference once; a trainer that keeps a state across
        optimiser steps (e.g. truncated backprop from ``state.detach()``) calls this so
        that the subtracted reference matches the weights again.
        """
        ep = dataclasses.replace(state.episode, attrs=self.hierarchy.aggregate_mean(self.splat_attrs))
        ep.reference, _ = self._reference_pass(self._rest_state(ep))
        return dataclasses.replace(state, episode=ep)

    def _rest_state(self, ep: Episode) -> SimState:
        """The initial (rest) state of an episode: x_{-1} = x_0, carried by identity deformations."""
        h = self.hierarchy
        L = h.root_level
        nl = L + 1
        dev, dt_ = ep.rest[0].device, ep.rest[0].dtype
        eye = torch.eye(3, dtype=dt_, device=dev)
        ident_q = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dt_, device=dev)
        carry: list[Optional[torch.Tensor]] = [None] * nl
        deform: list[Optional[torch.Tensor]] = [None] * nl
        carry[L] = ep.rest[L]
        deform[L] = eye.expand(1, 3, 3).clone()
        for l in range(L - 1, -1, -1):
            carry[l] = carry[l + 1].index_select(0, h.parents[l]) + _gather_matvec(deform[l + 1], h.parents[l], ep.offsets[l])
            if l >= 1 or self.config.gnn.splat_head:
                deform[l] = eye.expand(h.sizes[l], 3, 3).clone()
        sim = set(self.sim_levels)
        zeros = [torch.zeros_like(c) for c in carry]
        state = SimState(
            step=0, positions=list(carry), prev_positions=list(carry), carry=list(carry), carry_prev=list(carry),
            resid=zeros, resid_prev=list(zeros),
            rot=[ident_q.expand(h.sizes[l], 4).clone() if l in sim else None for l in range(nl)],
            deform=deform, means=carry[0], covs=ep.rest_covs, quats=ep.rest_quats, episode=ep,
            control_points=None, dyn_edges=[None] * nl, dyn_step=[0] * nl,
        )
        state.covs, state.quats = self._splat_shape(state.deform, state.rot, ep)
        return state

    def _reference_pass(self, rest_state: SimState) -> tuple[list[Optional[torch.Tensor]], list[Optional[torch.Tensor]]]:
        """(raw network outputs per level, dynamic edges) at the rest state under the reference
        forces, computed exactly as a step at rest computes them (zero update applied)."""
        f_ref = self.forces(rest_state, None, reference_only=True)
        if rest_state.episode.reference_mode == "force_free":
            f_ref = torch.zeros_like(f_ref)
        nxt, raw = self._advance(rest_state, None, f_ref, None)
        return raw, nxt.dyn_edges

    # ------------------------------------------------------------------ step
    def effect_context(self, state: SimState, action: Optional[RobotAction]) -> EffectContext:
        ep = state.episode
        dt = ep.scene.dt
        x = state.positions[0]
        v = (x - state.prev_positions[0]) / dt
        cp = cpv = grip = None
        if action is not None:
            cp = action.control_points.to(device=x.device, dtype=x.dtype)
            if state.control_points is not None and state.control_points.shape == cp.shape:
                cpv = (cp - state.control_points) / dt
            else:
                cpv = torch.zeros_like(cp)
            grip = torch.as_tensor(action.gripper, dtype=x.dtype, device=x.device).reshape(())
        return EffectContext(
            positions=x, velocities=v, masses=ep.masses[0], attrs=ep.attrs[0], gravity=ep.scene.gravity,
            plane_normal=ep.scene.plane_normal, plane_offset=ep.scene.plane_offset, dt=dt,
            control_points=cp, control_velocities=cpv, gripper=grip, rest_positions=ep.rest[0], cache=ep.cache,
            state_in=state.aux, state_out={}, time=float(state.step) * float(dt),
        )

    def forces(self, state: SimState, action: Optional[RobotAction], reference_only: bool = False) -> torch.Tensor:
        """Total external force on every splat [N0, 3] (newtons) at this state."""
        return self.effects(self.effect_context(state, action), reference_only=reference_only)

    def step(self, state: SimState, action: Optional[RobotAction] = None) -> SimState:
        """One step t -> t+1 under robot action R_{t+1} (None: no robot)."""
        if state.episode.reference is None or len(state.episode.reference) != self.num_levels:
            raise RuntimeError("step: state has no reference outputs; make it with Simulator.init_state")
        if not self.is_bound or [x.shape[0] for x in state.positions] != self.hierarchy.sizes:
            raise ValueError(
                f"step: state has level sizes {[x.shape[0] for x in state.positions]}, this simulator "
                f"{None if self.hierarchy is None else self.hierarchy.sizes} (a state of another model?)"
            )
        if action is not None and not isinstance(action, RobotAction):
            raise TypeError(f"step: action must be a RobotAction or None, got {type(action).__name__}")
        dyn = self.config.dynamics
        # a physics prior carries its own table, friction and gravity: the rule is for models without one
        passive_rule = dyn.passive_friction is not None and self.effects.physics_host is None
        exempt = dyn.passive_exempt
        if exempt and dyn.passive_exempt_closed and (action is None or action.is_open):
            exempt = []  # an open gripper's coupling drags, it does not carry: the step stays passive
        ctx = self.effect_context(state, action)
        f, f_direct, acting = self.effects.split_active(ctx, check_active=passive_rule, exempt=exempt)
        nxt, _ = self._advance(state, action, f, state.episode.reference, f_direct, passive=acting if passive_rule else 2)
        nxt.aux = ctx.state_out  # what the effects carry to the next step
        if not bool(torch.isfinite(nxt.positions[0]).all()):
            raise SimulationDiverged(f"step: non-finite positions after the step (effects: "
                                     f"{', '.join(s.instance_key for s in self.effects.specs) or 'none'})")
        return nxt

    forward = step

    def trained_terms(self) -> list[str]:
        """The effect keys other than the reference ones (gravity, the support) and those fitted
        after training (``EffectSpec.fitted_after_training``): the terms the network was trained
        with beyond its equilibrium, e.g. its robot coupling (``passive_exempt``)."""
        return [s.instance_key for s in self.effects.specs
                if not self.effects[s.instance_key].in_reference and not s.fitted_after_training]

    def set_network(self, on: bool) -> "Simulator":
        """Switch the learned network's contribution on or off. Off, every level's network output is
        exactly zero (the network is not run), so a step is the physical terms alone: the reference
        effects' equilibrium, the direct effects (the robot coupling, the physics prior) and the bounds.
        A model whose decoder's last layer is zero (``gnn.out_init_scale: 0``, the untrained network
        of the ``tiny`` training config) rolls out bit for bit the same with the network on or off.
        Not part of the weights (``state_dict``). Returns self."""
        self.network_enabled = bool(on)
        return self

    def set_passive_friction(self, mu: Optional[float], exempt: Optional[Sequence[str]] = None,
                             exempt_closed: Optional[bool] = None) -> "Simulator":
        """Switch the passive-object rule (``DynamicsConfig.passive_friction``): None leaves the
        model's setting, a negative value turns it off, any other is its friction coefficient.
        ``exempt``: effect keys whose steps are not passive (``DynamicsConfig.passive_exempt``;
        None leaves the setting); ``exempt_closed``: only while the gripper is closed
        (``DynamicsConfig.passive_exempt_closed``; None leaves it)."""
        if mu is not None:
            self.config.dynamics.passive_friction = None if mu < 0 else float(mu)
        if exempt is not None:
            unknown = [k for k in exempt if k not in self.effects.terms]
            if unknown:
                raise ValueError(f"set_passive_friction: no effect {unknown[0]!r} (has {', '.join(self.effects.terms)})")
            self.config.dynamics.passive_exempt = list(exempt)
        if exempt_closed is not None:
            self.config.dynamics.passive_exempt_closed = bool(exempt_closed)
        self.config.dynamics.validate()
        return self

    def rollout(self, state: SimState, actions: Sequence[Optional[RobotAction]]) -> list[SimState]:
        """States after each action (len(actions) of them); differentiable under autograd."""
        out = []
        for a in actions:
            state = self.step(state, a)
            out.append(state)
        return out

    # ------------------------------------------------------------------ internals
    def _edges(self, state: SimState, l: int) -> tuple[torch.Tensor, Optional[torch.Tensor], int]:
        """(static edges, dynamic edges or None, step they were built at) for level l at this state."""
        g = self.config.graph
        static = self.graphs.static[l]
        if not g.dynamic_edges or state.positions[l].shape[0] < 2:
            return static, None, state.step
        cached = state.dyn_edges[l] if l < len(state.dyn_edges) else None
        if cached is not None and state.step - state.dyn_step[l] < g.dynamic_every:
            return static, cached, state.dyn_step[l]
        radii = g.dynamic_radii or g.radii
        dyn = dynamic_edges(
            state.positions[l].detach(), g.k, float(radii[l]), self.graphs.static_keys[l], g.knn_backend,
            self.graphs.static_lookup[l],
        )
        return static, dyn, state.step

    def _level_graph(
        self, l: int, state: SimState, static: torch.Tensor, dyn: Optional[torch.Tensor]
    ) -> tuple[MessageGraph, torch.Tensor]:
        """Message graph and normalised edge features [E, 10] of level l: the static edges
        (in their padded dense layout where the level has one) followed by the dynamic ones."""
        ep, dt = state.episode, state.episode.scene.dt
        vs = self.config.dynamics.velocity_scale
        x, xp = state.positions[l], state.prev_positions[l]
        vel = (x - xp) / dt
        n = x.shape[0]
        has_dyn = dyn is not None and dyn.shape[1] > 0
        feats = [edge_features(x, vel, ep.rest[l], static, 0.0, vs, ep.static_rest_vectors[l])]
        if has_dyn:
            feats.append(edge_features(x, vel, ep.rest[l], dyn, 1.0, vs))
        ef = torch.cat(feats, dim=0) if has_dyn else feats[0]
        if ep.network_frame is not None:  # the direction (0:3) and the relative velocity (4:7) turned
            Qt = ep.network_frame.T
            ef = torch.cat([ef[:, 0:3] @ Qt, ef[:, 3:4], ef[:, 4:7] @ Qt, ef[:, 7:]], dim=-1)
        ef = self.edge_norms[l](ef)
        dense = self.graphs.dense[l]
        deg = self.graphs.static_degree[l]
        n_static = static.shape[1]
        if dense is not None:
            ef_static = ef.new_zeros((n * dense.k, ef.shape[1])).index_copy(0, dense.slots, ef[:n_static])
            mask = None if dense.mask is None else dense.mask.to(ef.dtype)
            send, recv, k = dense.senders, dense.receivers, dense.k
        else:
            ef_static, send, recv, mask, k = ef[:n_static], static[0], static[1], None, 0
        if has_dyn:
            ef = torch.cat([ef_static, ef[n_static:]], dim=0)
            send = torch.cat([send, dyn[0]])
            recv = torch.cat([recv, dyn[1]])
            if mask is not None:
                mask = torch.cat([mask, mask.new_ones((dyn.shape[1], 1))])
            deg = deg + torch.bincount(dyn[1], minlength=n)
        else:
            ef = ef_static
        degf = deg.to(ef.dtype)
        graph = MessageGraph(send, recv, n, k, mask, 1.0 / degf.clamp_min(1.0), (degf > 0).to(ef.dtype))
        return graph, ef

    def _node_features(self, l, a_anchor, a_ext, v_rel, attrs, turn=None) -> torch.Tensor:
        d = self.config.dynamics
        vec = torch.cat([a_anchor / d.accel_scale, a_ext / d.accel_scale, v_rel / d.velocity_scale], dim=-1)
        if turn is not None:  # row vectors: v' = v Q^T, three at a time
            vec = (vec.reshape(-1, 3, 3) @ turn.T).reshape(-1, 9)
        return self.node_norms[l](torch.cat([vec, attrs], dim=-1))

    def _advance(
        self,
        state: SimState,
        action: Optional[RobotAction],
        forces: torch.Tensor,
        reference: Optional[list[Optional[torch.Tensor]]],
        direct: Optional[torch.Tensor] = None,
        passive: int = 2,
    ) -> tuple[SimState, list[Optional[torch.Tensor]]]:
        """Apply one step with splat forces [N0, 3]. ``reference`` None = reference pass
        (zero update, raw outputs returned); else outputs minus reference drive the update.
        ``direct`` [N0, 3]: the part of ``forces`` from direct effects, also integrated as an
        explicit acceleration (root: mean; lower levels: excess over the parent's).
        ``passive``: below 2, apply the passive-object rule to the root (:meth:`_passive_root`;
        0 = untouched, 1 = only direct non-reference forces act; see ``EffectSet.split_active``)."""
        h, ep, cfg = self.hierarchy, state.episode, self.config
        dyn_cfg = cfg.dynamics
        # the passive rule's "nothing holds it up": untouched, or only direct forces with the gripper
        # open (an open gripper's coupling drags, it does not carry)
        free = passive == 0 or (passive == 1 and action is not None and action.is_open)
        L = h.root_level
        nl = L + 1
        dt = ep.scene.dt
        n0 = h.sizes[0]
        if tuple(forces.shape) != (n0, 3):
            raise ValueError(f"_advance: forces must be [{n0}, 3], got {list(forces.shape)}")
        f_lv = h.aggregate_sum(forces)
        a_direct: Optional[list[torch.Tensor]] = None
        if direct is not None:
            if tuple(direct.shape) != (n0, 3):
                raise ValueError(f"_advance: direct forces must be [{n0}, 3], got {list(direct.shape)}")
            a_direct = [f / m.clamp_min(1e-12)[:, None] for f, m in zip(h.aggregate_sum(direct), ep.masses)]
        new_pos: list[Optional[torch.Tensor]] = [None] * nl
        new_carry: list[Optional[torch.Tensor]] = [None] * nl
        new_resid: list[Optional[torch.Tensor]] = [None] * nl
        new_rot: list[Optional[torch.Tensor]] = [None] * nl
        new_def: list[Optional[torch.Tensor]] = [None] * nl
        latents: list[Optional[torch.Tensor]] = [None] * nl
        raw: list[Optional[torch.Tensor]] = [None] * nl
        dyn_edges = list(state.dyn_edges) + [None] * (nl - len(state.dyn_edges))
        dyn_step = list(state.dyn_step) + [state.step] * (nl - len(state.dyn_step))
        sim_levels = self.sim_levels
        net_sq: list[torch.Tensor] = []  # the network's contribution per level (SimState.network_sq)

        for l in range(L, -1, -1):
            # where the anchor carries each node at t+1
            if l == L:
                c_new = ep.rest[L]
            else:
                p = h.parents[l]
                c_new = new_pos[l + 1].index_select(0, p) + _gather_matvec(new_def[l + 1], p, ep.offsets[l])
            new_carry[l] = c_new
            if l not in sim_levels:  # splats without a head: carried rigidly-affinely by their cluster
                new_resid[l] = state.resid[l]
                new_pos[l] = c_new
                continue
            a_anchor = (c_new - 2.0 * state.carry[l] + state.carry_prev[l]) / (dt * dt)
            v_rel = (state.resid[l] - state.resid_prev[l]) / dt
            if not self.network_enabled:  # the physical terms alone: the network's output is exactly zero
                if l >= 1:
                    _, dyn, built = self._edges(state, l)
                    dyn_edges[l], dyn_step[l] = dyn, built
                out = v_rel.new_zeros((h.sizes[l], HEAD_OUTPUTS))
            else:
                a_ext = f_lv[l] / ep.masses[l].clamp_min(1e-12)[:, None]
                nodes = self._node_features(l, a_anchor, a_ext, v_rel, ep.attrs[l], ep.network_frame)
                parent_lat = None
                if l < L and cfg.gnn.top_down_latent:
                    parent_lat = latents[l + 1].index_select(0, h.parents[l])
                if l >= 1:
                    static, dyn, built = self._edges(state, l)
                    dyn_edges[l], dyn_step[l] = dyn, built
                    graph, efeat = self._level_graph(l, state, static, dyn)
                    out, lat = self.gnn.forward_level(nodes, graph, efeat, parent_lat)
                    latents[l] = lat
                else:
                    out = self.gnn.forward_splats(nodes, latents[1].index_select(0, h.parents[0]))
            raw[l] = out
            delta = torch.zeros_like(out) if reference is None else out - reference[l]
            if self.network_enabled and reference is not None:
                net_sq.append((delta * delta).sum(-1).mean())
            # translation: residual velocity and offset, bounded
            acc = dyn_cfg.accel_scale * delta[:, :3]
            turn = ep.network_frame
            if turn is not None:  # back to the world frame: a = Q^T a'
                acc = acc @ turn
            a_d = None
            if a_direct is not None:  # residual physics: own direct acceleration minus the anchor's
                a_d = a_direct[l] if l == L else a_direct[l] - a_direct[l + 1].index_select(0, h.parents[l])
            if passive < 2 and l == L and reference is not None:
                v_new = _clamp_norm(self._passive_root(v_rel, v_rel + dt * acc, a_d, state, untouched=free),
                                    dyn_cfg.max_speed)
            else:
                if a_d is not None:
                    acc = acc + a_d
                v_new = v_rel + dt * acc
                if free and reference is not None:
                    # nothing holds the object: its parts' motion relative to their anchors may not
                    # gain either (a model that never saw a release otherwise lets them creep up)
                    v_new = _no_gain(v_rel, v_new, ep.scene.plane_normal.to(v_new),
                                     float(ep.scene.gravity.norm()) * float(dt), True)
                v_new = _clamp_norm(v_new, dyn_cfg.max_speed)
            d_new = state.resid[l] + dt * v_new
            if l < L:
                d_new = _clamp_norm(d_new, ep.residual_limit[l])
            new_resid[l] = d_new
            new_pos[l] = c_new + d_new
            # deformation: F = U diag(s) V^T R, R' = U V^T R
            U = _quat_from_raw(delta[:, 3:7])
            V = _quat_from_raw(delta[:, 7:11])
            s_max = dyn_cfg.max_log_stretch
            ls = s_max * torch.tanh(delta[:, 11:14] / s_max)
            ls = ls - ls.mean(dim=-1, keepdim=True)
            r_old = state.rot[l]
            if turn is None:
                new_rot[l] = quat_normalize(quat_multiply(quat_multiply(U, quat_conjugate(V)), r_old))
                F = (quat_to_rotmat(U) * ls.exp()[:, None, :]) @ (quat_to_rotmat(V).transpose(-1, -2) @ quat_to_rotmat(r_old))
            else:  # the update D' = U' S V'^T back in the world frame, D = Q^T D' Q, written so that
                # D' = I gives exactly I (the rest fixed point): I + Q^T (D' - I) Q; its rotation
                # U' V'^T as a quaternion whose vector part is turned back
                m = quat_multiply(U, quat_conjugate(V))
                m = torch.cat([m[:, :1], m[:, 1:] @ turn], dim=-1)
                new_rot[l] = quat_normalize(quat_multiply(m, r_old))
                eye = torch.eye(3, dtype=U.dtype, device=U.device)
                D = (quat_to_rotmat(U) * ls.exp()[:, None, :]) @ quat_to_rotmat(V).transpose(-1, -2)
                D = eye + turn.T @ (D - eye) @ turn
                F = D @ quat_to_rotmat(r_old)
            new_def[l] = F if l == L else F @ new_def[l + 1].index_select(0, h.parents[l])

        nxt = SimState(
            step=state.step + 1,
            positions=new_pos,
            prev_positions=list(state.positions),
            carry=new_carry,
            carry_prev=list(state.carry),
            resid=new_resid,
            resid_prev=list(state.resid),
            rot=[new_rot[l] if l in sim_levels else None for l in range(nl)],
            deform=new_def,
            means=new_pos[0],
            covs=ep.rest_covs,
            quats=ep.rest_quats,
            episode=ep,
            control_points=None if action is None else action.control_points.to(new_pos[0]),
            dyn_edges=dyn_edges,
            dyn_step=dyn_step,
            network_sq=torch.stack(net_sq).mean() if net_sq else None,
        )
        nxt.covs, nxt.quats = self._splat_shape(new_def, nxt.rot, ep)
        return nxt, raw

    def _passive_root(self, v_old: torch.Tensor, v_net: torch.Tensor, a_direct: Optional[torch.Tensor],
                      state: SimState, untouched: bool = False) -> torch.Tensor:
        """The passive-object rule (``DynamicsConfig.passive_friction``): the root's residual
        velocity [1, 3] after a step, from the previous one ``v_old``, the network's update
        ``v_net`` and the direct effects' root acceleration ``a_direct`` ([1, 3] or None).

        Applied on steps where every force but gravity and the support is either zero or
        integrated directly (``EffectSet.split_active``): the network's root output is then the
        object's response to gravity and the support, which can make it fall, stop a fall and
        brake a slide, but give it no horizontal momentum and no upward speed (u: along the
        table normal, h: perpendicular to it). So

        1. the network's update may not raise the horizontal speed |v_h| above the previous
           one, nor v_u above max(previous v_u, 0) -- above max(previous v_u - |g| dt, 0) when
           nothing holds the object up (``untouched``: no non-reference force at all, or only
           direct ones with the gripper open; a rising object slows down at least as fast as
           under gravity). Falling and slowing down are the network's;
        2. the direct effects' acceleration is added (robot coupling, wind);
        3. while the object rests on the support (its lowest splat within ``passive_contact_m``
           of its lowest height in the episode's initial state): the support takes the fraction
           f of a downward v_u, f the mass fraction of splats at or below their own resting
           height (+ ``passive_contact_m``), so a closed gripper pressing a lying object down
           does not push it through the table while a hanging one still comes down onto it;
           an object more than half of which lies deeper than that is pushed back up by half its
           median depth per step, at most at |g| dt; and Coulomb friction takes
           mu |g| dt off |v_h|, down to 0 (a direct push weaker than mu |g| moves nothing, a
           stronger one accelerates by the excess).

        It bounds what a learned model driven outside its training data can do: without it a
        model that is off by a small force in a new resting configuration accelerates the
        object away, step after step.
        """
        ep, dyn = state.episode, self.config.dynamics
        up, d = ep.scene.plane_normal, ep.scene.plane_offset
        g_dt = float(ep.scene.gravity.norm()) * float(ep.scene.dt)

        def parts(v):
            vu = (v * up).sum(-1, keepdim=True)
            return vu, v - vu * up

        v = _no_gain(v_old, v_net, up, g_dt, untouched)
        if a_direct is not None:
            v = v + float(ep.scene.dt) * a_direct
        height = state.positions[0] @ up + d  # [N0]
        rest_height = ep.rest[0] @ up + d
        if bool(height.min() <= rest_height.min() + dyn.passive_contact_m):
            vu, vh = parts(v)
            # the support: the mass fraction f of the splats at (or below) their resting height
            # cannot be pushed on into the table, so the object's downward speed keeps (1 - f)
            m0 = ep.masses[0]
            f = (m0 * (height <= rest_height + dyn.passive_contact_m).to(m0.dtype)).sum() / m0.sum().clamp_min(1e-30)
            vu = torch.where(vu < 0, vu * (1.0 - f), vu)
            # and it pushes back an object sunk into it: half the median depth below the
            # splats' resting heights per step, when more than half of it is below them
            sunk = torch.median(rest_height - dyn.passive_contact_m - height)
            if bool(sunk > 0):  # at most |g| dt: the untouched cap takes it off again the next step
                push = (0.5 * sunk / float(ep.scene.dt)).clamp_max(g_dt)
                vu = torch.maximum(vu, push.reshape(1, 1).to(vu))
            mu = float(dyn.passive_friction)
            if mu > 0:
                sh = vh.norm(dim=-1, keepdim=True)
                vh = vh * ((sh - mu * g_dt).clamp_min(0.0) / sh.clamp_min(1e-30))
            v = vu * up + vh
        return v

    def _splat_shape(self, deform, rot, ep: Episode) -> tuple[torch.Tensor, torch.Tensor]:
        """Splat covariances Fbar Sigma Fbar^T [N0,3,3] and quaternions Rbar q_rest [N0,4]."""
        h = self.hierarchy
        L = h.root_level
        if deform[0] is not None:
            F0 = deform[0]
        else:
            F0 = deform[1].index_select(0, h.parents[0])
        covs = F0 @ ep.rest_covs @ F0.transpose(-1, -2)
        # accumulated rotation product, root first
        rbar = rot[L]
        for l in range(L - 1, 0, -1):
            rbar = quat_multiply(rot[l], rbar.index_select(0, h.parents[l]))
        rbar0 = rbar.index_select(0, h.parents[0])
        if rot[0] is not None:
            rbar0 = quat_multiply(rot[0], rbar0)
        quats = quat_normalize(quat_multiply(rbar0, ep.rest_quats))
        return covs, quats

    # ------------------------------------------------------------------ losses / diagnostics
    def momentum_loss(self, state: SimState) -> torch.Tensor:
        """SoMA's mass-consistency term between adjacent levels (scalar):
        sum_l sum_c |m_c x_c - sum_{i in children(c)} m_i x_i|^2 over the cluster levels
        (positions of this state, masses of its episode). Zero at the initial state up to
        float rounding; nodes of different levels move independently otherwise."""
        h, ep = self.hierarchy, state.episode
        total = state.means.new_zeros(())
        for l in range(h.root_level):
            child = (ep.masses[l][:, None] * state.positions[l])
            summed = torch.zeros_like(state.positions[l + 1]).index_add_(0, h.parents[l], child)
            diff = ep.masses[l + 1][:, None] * state.positions[l + 1] - summed
            total = total + (diff * diff).sum()
        return total

    def extent_bound(self, state: SimState) -> torch.Tensor:
        """[N0] structural bound on |x_splat - x_root| at any step (m): sum over levels of
        stretch_max^(levels above) x rest offset + residual limit (see module docstring)."""
        h, ep = self.hierarchy, state.episode
        L = h.root_level
        smax = math.exp(2.0 * self.config.dynamics.max_log_stretch)
        bound = torch.zeros(1, dtype=ep.rest[L].dtype, device=ep.rest[L].device)
        for l in range(L - 1, -1, -1):
            p = h.parents[l]
            nF = smax ** (L - l)  # |Fbar| of the anchor: product of L - l local F's
            b = bound.index_select(0, p) + nF * ep.offsets[l].norm(dim=-1)
            if l in self.sim_levels:
                b = b + ep.residual_limit[l]
            bound = b
        return bound
