"""Physics prior: a position-based model of the object that drives the learned dynamics.

Effect ``physics`` (registry; ``direct``, ``feature: false`` in the training configs that use
it). Why: on a CPU training budget the hierarchical network learns little beyond its priors
(README "Accuracy"), and the robot coupling's carry lifts an object as a rigid whole, while a
rope grasped near one end and lifted hangs from the fingers down to the table
(docs/discrepancy.md, "A physics prior"). A term the network never saw (wind, a slipping grip)
moves a learned model only as a force integrated on top of it, which a held object answers
with a drift, not a swing. This term gives the object physical behaviour -- it hangs, it is
inextensible, the table carries and brakes it, the gripper holds and pushes it -- and gives
the discrepancy workflow's candidate effects (wind, drag, table friction, a slipping grip,
mass, stiffness) a physical meaning: they act inside this model (:class:`PhysicsMods`).

Model (per step t -> t+1; the grasp, and with ``carry_velocity`` a velocity lag, carried in the simulator's state)
------------------------------------------------------------------------------------------------------------------
* **Nodes.** ``num_nodes`` farthest-point samples of the episode's initial splats; every splat
  belongs to its nearest sample's cell, a node is its cell's centre of mass and moves with
  it (position and velocity = the mass-weighted means of its splats' at t).
* **Constraints** between nodes (rest lengths from the initial state): stretch to the nearest
  ``neighbors`` within ``spring_radius_factor`` x the median node spacing, bending to the next
  ``bend_neighbors`` out to ``bend_radius_factor`` x spacing; solved by ``iterations``
  over-relaxed Jacobi passes per substep with per-constraint compliances (XPBD form, per unit
  rest length), or (``solver: newton``) by ``newton_iterations`` Gauss-Newton steps on the whole
  node system (:func:`_newton_project`). Long bending pairs make a rope or cloth as stiff as its
  compliances say with the Gauss-Newton solve; with a few Jacobi passes the passes, not the
  compliances, set how stiff a long object is.
  **Rod** (``bend_model: rod``, ropes, Newton solver): the nodes are instead cells of equal length
  along the rope's centre line (:func:`centre_line_cells`), stretch acts between consecutive ones
  and bending on consecutive triples with an elastic rod's energy, quadratic in the turning angle
  from the rest shape (:func:`_newton_project`). A distance pair's length changes only to second
  order in a small bend, so the pairs' bending has no stiffness at small angles and grows with the
  bend; a rope held near one end then leaves the fingers straighter and kinks further out than an
  elastic rod does.
* **Gravity** from the scene, still-air damping ``exp(-damping h)`` per substep.
* **Table**: a node may not go below its initial height above the plane (capped at
  ``contact_offset_max``, so nodes resting on the table stay where they were reconstructed);
  pushed below it is projected back and its tangential displacement is reduced by Coulomb
  friction ``mu x depth``. The projection is a position correction: the node leaves the substep
  with no velocity away from the table (``inelastic_table``; otherwise a node that begins a
  substep below its floor keeps the push as velocity, and a rope landing on the table bounces).
* **Gripper** (the action at t+1; control points move linearly from t within the step): when
  the gripper closes, the nodes within ``attach_radius`` of the control points' centroid (where
  there is none, the nodes of the cells with a splat that close: the material between the
  fingers, however sparse the nodes) are grasped, each held at its offset to that centroid
  (compliance ``grip_compliance``) until the gripper opens (:class:`Grasp`, carried in
  ``SimState.aux``); free nodes are pushed out of ``contact_radius`` around every control point.
  A **tilting grip** (``grip_tilt_compliance`` > 0, Newton solver, the hard grip): the held
  section may also turn about the closing axis, on a rotational spring, as a rope pinched between
  two pads turns under a long arm's weight (the reference world's soft grasp constraints tilt its
  held section about 19 degrees when the rope is held 3 to 5 of 25 vertices from an end).
  A **compliant grip** (``PhysicsMods.grip`` = g > 0, gripper_slip's ``loosen``) replaces the held
  nodes' hard constraint by a spring-damper to their place in the fingers that carries the whole
  object: hanging rigidly in it, the object would be a critically damped oscillator of time
  constant ``tau = GRIP_TAU0 (e^(2 g) - 1)`` (0.05 s x: g = 0.5 -> 0.086 s, 1 -> 0.32 s,
  1.5 -> 0.95 s), its static sag g_0 tau^2 (7 cm, 1 m, 9 m). Solved implicitly per substep
  (stable for any tau): a grip from stiff (g -> 0, the hard grip) through a soft one whose load
  sags out of the fingers as it is carried, to one that holds nothing.
  g < 0: a tighter grip (the compliance x e^(3 g)).
  A **friction-limited grip** (``PhysicsMods.release`` = r != 0, gripper_slip's ``weaken``): the
  fingers' friction carries at most ``e^(-r)`` of the object's nominal weight (r = 0.5 -> 0.61,
  1 -> 0.37, 2 -> 0.14; r < 0: more than the weight, which only a heavier object, ``mods.mass``,
  can exceed; r = 0: no limit). The load is the weight of the part off the table, quasi-static (the grip carries
  what the table does not; inertia neglected): each node counts ``smoothstep`` of its height
  above its floor between ``release_d0`` and ``release_d1`` times its mass (times the mass
  factor). At the end of a step whose load exceeds the grip's capacity the object slides out
  of the fingers and falls free: the grasp is lost (a :class:`Grasp` holding nothing) until the
  gripper opens and closes again. An event, not differentiable in r (the workflow's fit finds r
  on its grid start, ``soma_ros.discrepancy.workflow._grid_start``).
* ``substeps`` per step. The nodes' displacement over the step gives a velocity change per
  node, carried to the splats by linear-blend skinning (``skin_neighbors`` nearest nodes); the
  term's force makes the fraction ``gain`` of it happen:
  ``F_i = m_i gain sum_k W_ik (v_k' - v_k) / dt``. The network adds its own motion on top.
  A step starts from the nodes' velocities as the simulator has them (the splats' mean velocity
  over the last step); with ``carry_velocity`` from the prior's own end-of-step velocities instead,
  the difference carried to the next step in the simulator's state like the grasp (the mean
  velocity gains only half of gravity's velocity per step: :func:`pbd_step`).

At rest stays at rest: with no control point within ``reach`` of any node, every node at
exactly zero velocity and no modifier force, the force is exactly zero (no constraint solve),
so the simulator's rest fixed point holds bit for bit (:mod:`.simulator`).

Learnable: log compliances (stretch, bending, grip; the grip's tilt when on), log damping, friction,
the gain's logit.

Effect modifiers (:class:`PhysicsMods`, collected by :class:`~.effects.EffectSet` from the other
terms' ``physics_modifier``): ``accel`` [3] (a uniform field, m/s^2), ``pressure`` [3] (the part of
a field across a line's tangent or along a sheet's normal: wind on a rope or cloth), linear and
quadratic drag, a friction change, the grip's loosening (compliant grip, above), the mass excess
(a heavier object: the same gravity, relatively softer constraints and grip), a log stiffness factor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch
from torch import nn

from ..config import ConfigError
from .base import Effect, EffectContext, register_effect, smoothstep
from .mods import PhysicsMods
from ..spring_mass import farthest_point_sampling, neighbour_pairs, skin_weights

__all__ = ["GRIP_TAU0", "grip_time_constant", "PhysicsMods", "PhysicsLayout", "PhysicsPrior", "Grasp", "build_layout",
           "grasp_nodes", "pbd_step"]


GRIP_TAU0 = 0.05  # s: the compliant grip's time-constant scale (module docstring)


def grip_time_constant(g: torch.Tensor) -> torch.Tensor:
    """The compliant grip's time constant (s) for a loosening g > 0: ``GRIP_TAU0 (e^(2 g) - 1)``."""
    return GRIP_TAU0 * torch.expm1(2.0 * g)


@dataclass
class PhysicsLayout:
    """Constants of one episode (:func:`build_layout`): K nodes, E constraints, N splats."""

    node_of: torch.Tensor  # [N] long: the cell (node) of every splat
    node_mass: torch.Tensor  # [K]
    rest: torch.Tensor  # [K, 3] node rest positions (cell centres of mass)
    si: torch.Tensor  # [E]
    sj: torch.Tensor  # [E]
    rest_len: torch.Tensor  # [E]
    bend: torch.Tensor  # [E] bool: a bending pair (else stretch)
    degree: torch.Tensor  # [K] constraints per node
    floor: torch.Tensor  # [K] lowest signed distance to the table plane
    skin_idx: torch.Tensor  # [N, k]
    skin_w: torch.Tensor  # [N, k]
    spacing: float
    sheet: bool
    # bend_model "rod": the nodes are a chain along the object's centre line and bending acts on its
    # triples (a, i, b) = (i-1, i, i+1): tri [3, B]; tri_u0 [B, 3] the rest offset of node i from the
    # midpoint of a and b and tri_t0 [B, 3] the rest chord b - a (unit); tri_len [B] the mean rest
    # length of the two edges (None for "pairs")
    tri: Optional[torch.Tensor] = None
    tri_u0: Optional[torch.Tensor] = None
    tri_t0: Optional[torch.Tensor] = None
    tri_len: Optional[torch.Tensor] = None

    @property
    def num_nodes(self) -> int:
        return int(self.rest.shape[0])


@dataclass
class Grasp:
    """The nodes the closed fingers hold: ``held`` [K] bool and ``offset`` [K, 3] where each is held
    relative to the control points' centroid (the fingers closing further about it do not move
    it). Carried from step to step in ``SimState.aux`` while the gripper stays closed."""

    held: torch.Tensor
    offset: torch.Tensor


def _is_sheet(rest: torch.Tensor) -> bool:
    """Two comparable large extents and a thin third: a sheet (cloth); else a line or a volume."""
    if rest.shape[0] < 4:
        return False
    ev = torch.linalg.eigvalsh(torch.cov(rest.t().double())).clamp_min(0).sqrt()  # ascending std
    return bool(ev[1] > 0.3 * ev[2] and ev[0] < 0.2 * ev[1])


@torch.no_grad()
def centre_line_cells(x: torch.Tensor, k: int, neighbours: int = 10) -> tuple[torch.Tensor, int]:
    """Cells of a line object's points x [N, 3] along its centre line: ([N] cell index, cell count).

    The points' geodesic distance from one end of the object (shortest paths through the graph of
    each point's ``neighbours`` nearest ones, pieces of the cloud that a gap leaves unconnected
    joined by their closest pair of points; the end: the point farthest from an arbitrary one
    along the graph) is cut into ``k`` intervals of equal length, cell 0 at that end. Empty
    intervals (a gap in the cloud) are dropped, so the count can be below ``k``. The cells are in
    order along the line: cell i and i + 1 are neighbours."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components, dijkstra
    from scipy.spatial import cKDTree

    pts = x.detach().double().cpu().numpy()
    n = len(pts)
    nb = min(neighbours, n - 1)
    dist, idx = cKDTree(pts).query(pts, k=nb + 1)
    rows, cols, w = list(np.repeat(np.arange(n), nb)), list(idx[:, 1:].reshape(-1)), list(dist[:, 1:].reshape(-1))
    while True:
        g = coo_matrix((np.maximum(w, 1e-12), (rows, cols)), shape=(n, n)).tocsr()
        g = g.maximum(g.T)
        count, label = connected_components(g, directed=False)
        if count == 1:
            break
        inside = np.flatnonzero(label == label[0])  # join the first piece to its nearest point outside it
        outside = np.flatnonzero(label != label[0])
        d, j = cKDTree(pts[outside]).query(pts[inside])
        i = int(np.argmin(d))
        rows.append(int(inside[i]))
        cols.append(int(outside[j[i]]))
        w.append(float(d[i]))
    end = int(np.argmax(dijkstra(g, indices=0)))
    s = dijkstra(g, indices=end)
    b = np.floor(s / max(float(s.max()), 1e-12) * k).clip(0, k - 1).astype(np.int64)
    used, cell = np.unique(b, return_inverse=True)
    return torch.as_tensor(cell.reshape(-1), device=x.device), int(len(used))


@torch.no_grad()
def build_layout(rest_splats: torch.Tensor, masses: torch.Tensor, plane_normal: torch.Tensor,
                 plane_offset: torch.Tensor, p: "PhysicsPrior.Params") -> PhysicsLayout:
    """Nodes, constraints, floors and skinning of an episode from its initial splats [N, 3]."""
    x = rest_splats.detach()
    dev, dt_ = x.device, x.dtype
    n = int(x.shape[0])
    if n < 2:
        raise ValueError(f"physics prior: need at least 2 splats, got {n}")
    K = min(int(p.num_nodes), n)
    m = masses.detach().to(dt_)
    tri = tri_u0 = tri_t0 = tri_len = None
    if p.bend_model == "rod":
        node_of, K = centre_line_cells(x, K)
    else:
        seeds = x[farthest_point_sampling(x.cpu(), K).to(dev)]
        node_of = torch.cdist(x, seeds).argmin(dim=1)  # [N]
    node_mass = torch.zeros(K, dtype=dt_, device=dev).index_add_(0, node_of, m)
    keep = node_mass > 0  # every seed owns itself, but be safe
    if not bool(keep.all()):
        remap = torch.cumsum(keep.long(), 0) - 1
        node_of = remap[node_of]
        node_mass = node_mass[keep]
        K = int(keep.sum())
    rest = torch.zeros(K, 3, dtype=dt_, device=dev).index_add_(0, node_of, m[:, None] * x) / node_mass[:, None]
    if p.bend_model == "rod":  # a chain: stretch along consecutive nodes, bending on consecutive triples
        if K < 3:
            raise ValueError(f"physics prior (bend_model rod): need at least 3 nodes along the centre line, got {K}")
        i = torch.arange(K - 1)
        pairs = torch.stack([i, i + 1]).to(dev)
        is_bend = torch.zeros(K - 1, dtype=torch.bool, device=dev)
        spacing = max(float((rest[1:] - rest[:-1]).norm(dim=-1).median()), 1e-6)
        j = torch.arange(1, K - 1, device=dev)
        tri = torch.stack([j - 1, j, j + 1])
        tri_u0 = rest[j] - 0.5 * (rest[j - 1] + rest[j + 1])  # the rest shape as it lies: no force at rest
        tri_t0 = rest[j + 1] - rest[j - 1]
        tri_t0 = tri_t0 / tri_t0.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        tri_len = 0.5 * ((rest[j] - rest[j - 1]).norm(dim=-1) + (rest[j + 1] - rest[j]).norm(dim=-1)).clamp_min(1e-6)
    else:
        d = torch.cdist(rest, rest)
        d.fill_diagonal_(math.inf)
        spacing = max(float(d.min(dim=1).values.median()), 1e-6) if K > 1 else 1e-3
        dc = d.cpu()
        stretch = neighbour_pairs(dc, p.neighbors, p.spring_radius_factor * spacing)
        bend = neighbour_pairs(dc, p.bend_neighbors, p.bend_radius_factor * spacing, skip=p.neighbors)
        if bend.numel() and stretch.numel():  # a pair that is a stretch pair stays one
            ks = set((stretch[0] * K + stretch[1]).tolist())
            bend = bend[:, torch.tensor([int(a) * K + int(b) not in ks for a, b in bend.t()], dtype=torch.bool)]
        pairs = torch.cat([stretch, bend], dim=1).to(dev)
        is_bend = torch.cat([torch.zeros(stretch.shape[1], dtype=torch.bool),
                             torch.ones(bend.shape[1], dtype=torch.bool)]).to(dev)
    rest_len = (rest[pairs[0]] - rest[pairs[1]]).norm(dim=-1).clamp_min(1e-6)
    degree = torch.bincount(pairs.reshape(-1), minlength=K).to(dt_)
    nrm = plane_normal.detach().to(dt_)
    floor = (rest @ nrm + plane_offset.detach().to(dt_)).clamp(min=0.0, max=float(p.contact_offset_max))
    ci, w = skin_weights(x, rest, p.skin_neighbors, spacing)
    return PhysicsLayout(node_of=node_of, node_mass=node_mass, rest=rest, si=pairs[0], sj=pairs[1],
                         rest_len=rest_len, bend=is_bend, degree=degree, floor=floor, skin_idx=ci, skin_w=w.to(dt_),
                         spacing=spacing, sheet=_is_sheet(rest), tri=tri, tri_u0=tri_u0, tri_t0=tri_t0,
                         tri_len=tri_len)


def _pressure(lay: PhysicsLayout, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """The part of the field w [3] each node's surface element feels [K, 3]: along its normal
    (sheet) or across its tangent (line, volume), local shape from its stretch edges."""
    K = x.shape[0]
    st = ~lay.bend
    si, sj = lay.si[st], lay.sj[st]
    d = x[sj] - x[si]
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    o = (d[:, :, None] * d[:, None, :]).reshape(-1, 9)
    cov = x.new_zeros(K, 9).index_add(0, si, o).index_add(0, sj, o).reshape(K, 3, 3)
    cov = cov + 1e-6 * torch.eye(3, dtype=x.dtype, device=x.device)
    _, evecs = torch.linalg.eigh(cov)  # ascending
    if lay.sheet:
        nrm = evecs[..., :, 0]
        return (nrm @ w)[:, None] * nrm
    t = evecs[..., :, 2]
    return w[None, :] - (t @ w)[:, None] * t


def closing_axis(cp: torch.Tensor) -> Optional[torch.Tensor]:
    """The direction [3] (unit; its sign arbitrary) in which the fingers close, from control points
    [P, 3] laid out as :func:`soma_ros.core.robot.control_point_pattern` makes them: jaw +1's
    points, then jaw -1's, mirror images across the plane between the jaws. The line between the
    jaws' centroids; with the jaws touching (centroids under 0.1 mm apart), the normal of the
    first jaw's points. None where neither is defined: an odd count, or a jaw whose points are
    collinear while the jaws touch."""
    P = cp.shape[0]
    if P < 2 or P % 2:
        return None
    jaw = cp[: P // 2].double()
    d = jaw.mean(dim=0) - cp[P // 2:].double().mean(dim=0)
    if float(d.norm()) > 1e-4:
        return (d / d.norm()).to(cp.dtype)
    if P // 2 < 3:
        return None
    _, s, vh = torch.linalg.svd(jaw - jaw.mean(dim=0), full_matrices=False)
    if not float(s[1]) > 1e-6 * max(float(s[0]), 1e-12):
        return None
    return vh[2].to(cp.dtype)


def grasp_nodes(lay: PhysicsLayout, x: torch.Tensor, cp: torch.Tensor, p: "PhysicsPrior.Params",
                splats: Optional[torch.Tensor] = None) -> Optional[Grasp]:
    """The grasp a gripper closing now makes: the nodes within ``attach_radius`` of the control
    points' centroid; where there is none and the splat positions ``splats`` [N, 3] are given, the
    nodes of the cells with a splat that close (the material between the fingers: with nodes
    sparser than ``attach_radius``, a closing gripper would otherwise hold nothing wherever the
    node sampling put no cell centre near it). Each held node keeps its offset to the centroid
    (None: nothing there)."""
    centre = cp.mean(dim=0)
    held = (x.detach() - centre).norm(dim=-1) <= p.attach_radius  # [K]
    holds = bool(held.any())
    if not holds and splats is not None:
        near = (splats.detach() - centre).norm(dim=-1) <= p.attach_radius  # [N]
        held = held.index_fill(0, lay.node_of[near], True)
        holds = bool(near.any())
    if not holds:
        return None
    return Grasp(held, (x - centre).detach())


def pbd_step(lay: PhysicsLayout, x: torch.Tensor, v: torch.Tensor, gravity: torch.Tensor, plane_normal: torch.Tensor,
             plane_offset: torch.Tensor, dt: float, p: "PhysicsPrior.Params", coef: dict[str, torch.Tensor],
             cp0: Optional[torch.Tensor] = None, cp1: Optional[torch.Tensor] = None, grasp: Optional[Grasp] = None,
             mods: Optional[PhysicsMods] = None, return_velocity: bool = False):
    """(Node positions [K, 3] after one step of ``dt`` from positions x and velocities v [K, 3], the
    grasp after it[, with ``return_velocity`` the nodes' velocities [K, 3] at the end of the step]).

    The end velocity is the last substep's: under gravity alone it is v + g dt, while the step's
    mean velocity (x' - x) / dt is only v + g dt / 2 (substeps n: v + g dt (n + 1) / (2 n)). A caller
    that starts the next step from the mean velocity (as the simulator's finite-difference
    velocities are) gains only half of gravity's velocity per step: a free object falls at about
    g / 2 and a hanging one swings too slowly, while every static shape is unchanged
    (:class:`PhysicsPrior.Params` ``carry_velocity``).

    ``coef``: the learnable coefficients as tensors (``stretch``, ``bend``, ``grip`` compliances,
    ``damping``, ``friction``); ``cp0`` / ``cp1`` [P, 3]: the control points at t and t+1 (None:
    no robot); ``grasp``: the nodes the closed fingers hold (:func:`grasp_nodes`; None: none). A
    loosened grip (``mods.grip`` = g > 0) holds them by a critically damped spring-damper of time
    constant :func:`grip_time_constant` instead of the hard constraint: per substep, with the
    held node's velocity u and position error e relative to the fingers (e = the error after the
    substep if it moved with them), backward Euler gives u' = (u - h r w^2 e) / (1 + 2 h r w + h^2 r w^2),
    w = 1/tau, r = the object's mass / the held nodes' mass (the spring carries the whole object:
    hanging rigidly in it, the object is a critically damped oscillator of time constant tau;
    ``mods.mass`` divides r by the mass factor: the same spring, a heavier load). The hard grip and
    its tilt are compliances per unit node mass, as the rod's bending is: ``mods.mass`` scales the
    inertia and the hold's stiffness alike, so a heavier object is held as rigidly, and a hanging
    object k times heavier moves exactly as one with 1/k of the stretch and bending stiffness (as
    for an elastic rope, where only the ratio of weight to stiffness shapes a rigidly held
    object). The reference world's rope bends so, but its stretch comes from soft constraints whose
    stiffness follows the mass, so a heavier world rope stretches about as much as a lighter one.
    Differentiable in x, v, coef, mods and the grasp's offsets."""
    mods = mods or PhysicsMods()
    kept = grasp  # returned as it is: a lost grasp (holding nothing) stays lost while the gripper is closed
    if grasp is not None and not bool(grasp.held.any()):
        grasp = None
    h = float(dt) / p.substeps
    h2 = h * h
    stiff = torch.exp(mods.stiffness) if mods.stiffness is not None else None
    alpha = torch.where(lay.bend, coef["bend"], coef["stretch"]) / (h2 * lay.rest_len)  # [E]
    a_tri = None
    if lay.tri is not None:  # the rod's bending: compliance per unit node mass, coef x l^4 (see _newton_project)
        a_tri = coef["bend"] * lay.tri_len.to(x.dtype) ** 4 / h2  # [B]
        if stiff is not None:
            a_tri = a_tri / stiff
    if stiff is not None:
        alpha = alpha / stiff
    w_inv = 1.0 / (1.0 + mods.mass.clamp_min(-0.9)) if mods.mass is not None else x.new_ones(())  # per unit mass
    a_grip = coef["grip"] / h2
    if grasp is not None and cp0 is None:
        raise ValueError("pbd_step: a grasp needs the control points")
    omega = None  # the compliant grip's 1/tau (None: the hard grip)
    if mods.grip is not None and grasp is not None:
        if float(mods.grip.detach()) > 0.0:
            omega = 1.0 / grip_time_constant(mods.grip).clamp_min(1e-6)
            # the spring holds the whole object: per unit of held mass its stiffness and damping are
            # the object's mass / the held nodes' times those of a critically damped omega
            held_mass = (lay.node_mass * grasp.held.to(lay.node_mass.dtype)).sum().clamp_min(1e-12)
            load = lay.node_mass.sum() / held_mass * w_inv  # a heavier object (mods.mass) sags more in it
            grip_k = h * omega * omega * load  # the backward-Euler update's constants (docstring)
            grip_den = 1.0 + 2.0 * h * omega * load + h * grip_k
            v_f = (cp1.mean(dim=0) - cp0.mean(dim=0)) / float(dt)  # [3] the fingers' velocity
        else:
            a_grip = a_grip * torch.exp(3.0 * mods.grip)
    damp = torch.exp(-coef["damping"] * h)
    mu = coef["friction"].clamp_min(0.0)
    if mods.friction is not None:
        mu = (mu + mods.friction).clamp_min(0.0)
    acc0 = gravity.to(x.dtype)
    if mods.accel is not None:
        acc0 = acc0 + mods.accel.to(x.dtype)
    nrm = plane_normal.to(x.dtype)
    off = plane_offset.to(x.dtype)
    inv_deg = (p.relaxation / lay.degree.clamp_min(1.0))[:, None]
    heldf = grasp.held.to(x.dtype)[:, None] if grasp is not None else None
    for s in range(p.substeps):
        cps = None if cp0 is None else cp0 + ((s + 1) / p.substeps) * (cp1 - cp0)
        acc = acc0
        if mods.pressure is not None:
            acc = acc + _pressure(lay, x, mods.pressure.to(x.dtype))
        if mods.linear_drag is not None:
            acc = acc - mods.linear_drag * v
        if mods.quadratic_drag is not None:
            acc = acc - mods.quadratic_drag * v.norm(dim=-1, keepdim=True) * v
        v = (v + h * acc) * damp
        target = cps.mean(dim=0) + grasp.offset if heldf is not None else None  # [K, 3] where the fingers hold
        if omega is not None:  # the compliant grip: implicit critically damped spring to the fingers
            e = x + h * v_f - target
            u1 = ((v - v_f) - grip_k * e) / grip_den
            v = v + heldf * (v_f + u1 - v)
        q = x + h * v
        hard = heldf is not None and omega is None  # the hard grip holds the held nodes at target
        if p.solver == "newton":
            hinge = None
            if hard and "tilt" in coef:  # the held section may turn about the closing axis (grip_tilt_compliance)
                axis = closing_axis(cps.detach())
                if axis is not None:
                    axis = axis.to(x.dtype)
                    hinge = (cps.mean(dim=0), axis, h2 / (coef["tilt"] * w_inv),
                             _held_turn(x.detach(), grasp.held, grasp.offset.detach(), axis))
            q = _newton_project(lay, q, alpha, w_inv, (heldf[:, 0] / (a_grip * w_inv), target) if hard else None,
                                p.newton_iterations, a_tri, hinge)
        else:
            for _ in range(p.iterations):
                d = q[lay.sj] - q[lay.si]
                length = d.norm(dim=-1).clamp_min(1e-9)
                lam = -(length - lay.rest_len) / (2.0 * w_inv + alpha)  # [E]
                corr = (lam / length)[:, None] * d
                dq = torch.zeros_like(q).index_add(0, lay.si, -corr).index_add(0, lay.sj, corr)
                q = q + w_inv * dq * inv_deg
                if hard:
                    q = q + heldf * (target - q) * (1.0 / (1.0 + a_grip))  # w_inv / (w_inv + a_grip w_inv)
        if cps is not None:  # control points push free nodes out of their contact radius
            dmin, jmin = torch.cdist(q, cps).min(dim=-1)
            pen = (p.contact_radius - dmin).clamp_min(0.0)
            if bool((pen > 0).any()):
                dirn = (q - cps[jmin]) / dmin.clamp_min(1e-9)[:, None]
                free = 1.0 - heldf if heldf is not None else 1.0
                q = q + pen[:, None] * dirn * free
        depth = (lay.floor - (q @ nrm + off)).clamp_min(0.0)  # [K] the table
        touch = depth > 0  # [K]
        touching = bool(touch.any())
        if touching:
            q = q + depth[:, None] * nrm
            dxt = q - x
            dxt = dxt - (dxt @ nrm)[:, None] * nrm
            st = dxt.norm(dim=-1).clamp_min(1e-12)
            keepf = (1.0 - mu * depth / st).clamp_min(0.0)
            q = q - dxt * ((1.0 - keepf) * touch.to(q.dtype))[:, None]
        v = (q - x) / h
        if p.inelastic_table and touching:
            # a node the table pushed back out leaves the substep with no velocity away from it: the
            # push undoes a penetration (one that began before the substep included), it is not a
            # bounce (without this, 1 mm below the floor at a substep's start leaves it at 0.5 m/s)
            vn = v @ nrm
            v = v - (touch.to(v.dtype) * vn.clamp_min(0.0))[:, None] * nrm
        x = q
    release = float(mods.release.detach()) if mods.release is not None else 0.0
    if grasp is not None and release != 0.0:  # the load (times the mass factor, 1 / w_inv) against the capacity
        if _lifted_fraction(lay, x.detach(), nrm, off, p) / float(w_inv.detach()) > math.exp(-release):
            kept = Grasp(torch.zeros_like(grasp.held), grasp.offset)  # slid out of the fingers
    return (x, kept, v) if return_velocity else (x, kept)


@torch.no_grad()
def _lifted_fraction(lay: PhysicsLayout, x: torch.Tensor, nrm: torch.Tensor, off: torch.Tensor,
                     p: "PhysicsPrior.Params") -> float:
    """The fraction of the object's mass off the table (smoothstep of every node's height above
    its floor between ``release_d0`` and ``release_d1``): the load a grip carries, quasi-static."""
    lift = (x @ nrm + off) - lay.floor  # [K] height above the node's floor
    s = smoothstep((lift - p.release_d0) / (p.release_d1 - p.release_d0))
    return float((lay.node_mass * s).sum() / lay.node_mass.sum())


def _turn(o: torch.Tensor, axis: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Offsets o [K, 3] turned by the angle phi (rad, 0-d) about the unit axis [3] (Rodrigues)."""
    ax = axis.expand_as(o)
    return (o * torch.cos(phi) + torch.cross(ax, o, dim=-1) * torch.sin(phi)
            + ax * (o @ axis)[:, None] * (1.0 - torch.cos(phi)))


@torch.no_grad()
def _held_turn(x: torch.Tensor, held: torch.Tensor, offset: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """The angle (rad, 0-d) about the unit axis [3] that best turns the held nodes' grasp offsets
    [K, 3] onto where they are now (x [K, 3]; both centred on the held nodes' means, each taken
    across the axis): where the hinge's Gauss-Newton steps start (:func:`_newton_project`)."""
    o, r = offset[held], x[held]
    o = o - o.mean(dim=0)
    r = r - r.mean(dim=0)
    o = o - (o @ axis)[:, None] * axis
    r = r - (r @ axis)[:, None] * axis
    sin = (torch.cross(o, r, dim=-1) @ axis).sum()
    cos = (o * r).sum()
    if float(sin.abs() + cos.abs()) < 1e-12:
        return x.new_zeros(())
    return torch.atan2(sin, cos)


def _newton_project(lay: PhysicsLayout, q: torch.Tensor, alpha: torch.Tensor, w_inv: torch.Tensor,
                    hold: Optional[tuple[torch.Tensor, torch.Tensor]], iterations: int,
                    a_tri: Optional[torch.Tensor] = None,
                    hinge: Optional[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]] = None
                    ) -> torch.Tensor:
    """The constraint projection of a substep solved by Gauss-Newton on the whole node system
    (``solver: newton``), instead of Jacobi passes whose count, not the compliances, sets how stiff
    a long object can be. Minimises, from the inertial prediction q [K, 3],
    ``|q' - q|^2 / (2 w_inv) + sum_e C_e(q')^2 / (2 alpha_e) [+ sum_held k_i |q'_i - target_i|^2 / 2]``
    (C_e = length - rest length; the same energy the Jacobi passes descend) with ``iterations``
    dense steps (3K x 3K, Cholesky, float64). ``hold``: (k [K] per node, target [K, 3]), the hard grip
    as the stiff penalty the Jacobi passes apply (k = 1 / a_grip on held nodes, 0 elsewhere).
    ``a_tri`` [B]: the compliances of the rod's bending on the layout's triples (``bend_model: rod``;
    ``lay.tri``, rest offsets ``lay.tri_u0``, rest chords ``lay.tri_t0``):
    ``sum_b |u_b - R_b u0_b|^2 / (2 a_b)``, u_b = q'_i - (q'_a + q'_b) / 2 the offset of node i from
    the midpoint of its chain neighbours and R_b the smallest rotation
    taking the rest chord t0_b to the current one (q_b - q_a, taken at the start of each Gauss-Newton
    step), so the rest shape turns with the rod. For two edges of length l turning by theta from rest,
    |u - R u0| is about l theta / 2: a quadratic energy in the turning angle, an elastic rod's; for
    bending stiffness EI and mass per length rho A, a = rho A l^4 / (4 EI) per unit node mass (every
    node weighs alike here): the learnable coefficient ``bend`` is rho A / (4 EI), in s^2/m^4.
    ``hinge`` (centre [3], unit axis [3], k_phi, phi0; with ``hold``; ``grip_tilt_compliance`` > 0):
    the held section may turn in the fingers. The hold's targets become centre + R(phi) (target -
    centre), R(phi) the turn by phi about the axis through the centre, phi one more unknown of the
    solve (starting at phi0, the held nodes' present turn, :func:`_held_turn`) with the energy
    ``k_phi phi^2 / 2``: a rotational spring, turned by the arms' weight. R(phi) is linearised
    at each step's phi (Gauss-Newton).
    Differentiable in q, alpha, w_inv, the hold, the hinge's stiffness and the rod's compliances."""
    K = q.shape[0]
    si, sj = lay.si, lay.sj
    f64 = torch.float64
    q0 = q.to(f64)
    qd = q0
    kk = (1.0 / alpha).to(f64)  # [E]
    m = (1.0 / w_inv).to(f64)
    hk = ht = None
    if hold is not None:
        hk, ht = hold[0].to(f64), hold[1].to(f64)
    if hinge is not None:
        if hk is None:
            raise ValueError("_newton_project: a hinge needs the hold")
        h_c, h_ax, h_k = hinge[0].to(f64), hinge[1].to(f64), hinge[2].to(f64)
        h_o = ht - h_c  # [K, 3] the held nodes' offsets from the hinge's centre
        phi = hinge[3].to(f64)
    for _ in range(iterations):
        d = qd[sj] - qd[si]
        length = d.norm(dim=-1).clamp_min(1e-12)
        n = d / length[:, None]
        c = length - lay.rest_len.to(f64)
        blk = kk[:, None, None] * n[:, :, None] * n[:, None, :]  # [E, 3, 3]
        hb = qd.new_zeros(K, K, 3, 3)
        hb = hb.index_put((si, si), blk, accumulate=True).index_put((sj, sj), blk, accumulate=True)
        hb = hb.index_put((si, sj), -blk, accumulate=True).index_put((sj, si), -blk, accumulate=True)
        diag = m.expand(K).clone()
        ge = (kk * c)[:, None] * n  # dE/dq_j of each constraint (-that for q_i)
        g = m * (qd - q0)
        g = g.index_add(0, sj, ge).index_add(0, si, -ge)
        h_col = None
        if hk is not None:
            diag = diag + hk
            if hinge is None:
                g = g + hk[:, None] * (qd - ht)
            else:
                ro = _turn(h_o, h_ax, phi)  # [K, 3]
                tan = torch.cross(h_ax.expand_as(ro), ro, dim=-1)  # d(R o)/dphi
                e = qd - h_c - ro
                g = g + hk[:, None] * e
                h_col = -(hk[:, None] * tan).reshape(-1)  # d2E / dq dphi
                g_phi = -(hk * (e * tan).sum(-1)).sum() + h_k * phi
                h_pp = (hk * (tan * tan).sum(-1)).sum() + h_k
        if a_tri is not None:
            tri, u0, t0 = lay.tri, lay.tri_u0, lay.tri_t0
            kr = (1.0 / a_tri).to(f64)  # [B]
            cw = (-0.5, 1.0, -0.5)
            with torch.no_grad():  # the rest offset turned with the chord (lagged: constant in this step)
                ch = qd[tri[2]] - qd[tri[0]]
                ch = ch / ch.norm(dim=-1, keepdim=True).clamp_min(1e-12)
                a0 = t0.to(f64)
                vx = torch.cross(a0, ch, dim=-1)
                cc = (a0 * ch).sum(-1).clamp_min(-1.0 + 1e-6)
                ud = u0.to(f64)
                # Rodrigues: R u = u + v x u + v x (v x u) / (1 + c)
                vu = torch.cross(vx, ud, dim=-1)
                target = ud + vu + torch.cross(vx, vu, dim=-1) / (1.0 + cc)[:, None]
            u = qd[tri[1]] - 0.5 * (qd[tri[0]] + qd[tri[2]])  # [B, 3]
            gu = kr[:, None] * (u - target)  # dE/du
            eye = torch.eye(3, dtype=f64, device=qd.device)
            for r_ in range(3):
                g = g.index_add(0, tri[r_], cw[r_] * gu)
                for c_ in range(3):
                    hb = hb.index_put((tri[r_], tri[c_]), (cw[r_] * cw[c_]) * kr[:, None, None] * eye, accumulate=True)
        hmat = hb.permute(0, 2, 1, 3).reshape(3 * K, 3 * K) + torch.diag(diag.repeat_interleave(3))
        rhs = -g.reshape(-1, 1)
        if h_col is not None:  # phi: one more row and column
            hmat = torch.cat([torch.cat([hmat, h_col[:, None]], dim=1),
                              torch.cat([h_col, h_pp.reshape(1)])[None, :]], dim=0)
            rhs = torch.cat([rhs, -g_phi.reshape(1, 1)])
        chol, info = torch.linalg.cholesky_ex(hmat)  # no raise, no host sync
        step = torch.cholesky_solve(rhs, chol)
        if h_col is not None:
            phi = phi + step[-1, 0]
            step = step[:-1]
        # the system is positive definite whenever it is finite (m > 0, the blocks PSD): a failed
        # factorisation means non-finite state, handed on as NaN for Simulator.step to report
        # (SimulationDiverged), as the Jacobi passes do, instead of a LinAlgError mid-step
        qd = torch.where(info == 0, qd + step.reshape(K, 3), torch.full_like(qd, math.nan))
    return qd.to(q.dtype)


@register_effect("physics")
class PhysicsPrior(Effect):
    """The physics prior (module docstring). Needs the episode's initial splats
    (``EffectContext.rest_positions``) and a per-episode cache (``EffectContext.cache``)."""

    hosts_modifiers = True

    @dataclass
    class Params:
        num_nodes: int = 48
        neighbors: int = 8
        spring_radius_factor: float = 3.0
        bend_neighbors: int = 16
        bend_radius_factor: float = 16.0
        # "pairs": bending by distance constraints to the next bend_neighbors nodes (any shape);
        # "rod" (line objects, solver newton): nodes along the centre line, an elastic rod's bending
        # on consecutive triples with compliance bend_compliance x l^4 (_newton_project)
        bend_model: str = "pairs"
        skin_neighbors: int = 4
        substeps: int = 16
        iterations: int = 10  # Jacobi constraint passes per substep (solver: jacobi)
        solver: str = "jacobi"  # or "newton": a Gauss-Newton solve of the whole node system per substep
        newton_iterations: int = 2  # Gauss-Newton steps per substep (solver: newton)
        relaxation: float = 1.5
        attach_radius: float = 0.02  # m around the control points' centroid
        contact_radius: float = 0.006  # m around each control point
        contact_offset_max: float = 0.02  # m: floors of the nodes resting on the table
        grip_threshold: float = 0.5  # gripper state below it: closed
        reach: float = 0.05  # m: a control point this close to a splat disturbs the rest state
        stretch_compliance: float = 1e-9  # s^2 per m of rest length (learnable)
        bend_compliance: float = 1e-8
        grip_compliance: float = 1e-7
        # > 0 (solver newton): the held section may turn in the fingers about their closing axis, on a
        # spring of this compliance per unit node mass (s^2 rad / m^2; the rotational stiffness is
        # node mass / this); 0: it stays as it was grasped (learnable when > 0; :func:`_newton_project`)
        grip_tilt_compliance: float = 0.0
        damping: float = 1.0  # 1/s (learnable)
        friction: float = 1.0  # the table's (learnable)
        gain: float = 0.9  # fraction of the velocity change made per step (learnable, in (0, 1))
        release_d0: float = 0.02  # m above a node's floor: below it the table carries the node (release rule)
        release_d1: float = 0.05  # m: from here up the grip carries all of the node's weight
        inelastic_table: bool = True  # a node pushed out of the table gains no velocity away from it
        # each step starts from the nodes' velocities at the end of the prior's previous step (the
        # splats' finite-difference velocity plus the prior's own difference between its end and mean
        # velocity, carried in the state), not from the mean velocity over the step, which gains only
        # half of gravity's velocity per step (pbd_step)
        carry_velocity: bool = False

    def __init__(self, params, *, attr_dim: int = 0) -> None:
        super().__init__(params, attr_dim=attr_dim)
        p = params
        ints = ("num_nodes", "neighbors", "bend_neighbors", "skin_neighbors", "substeps", "iterations")
        if p.num_nodes < 2 or p.neighbors < 1 or p.bend_neighbors < 0 or p.skin_neighbors < 1 or p.substeps < 1 \
                or p.iterations < 1:
            raise ConfigError(f"effect physics: {', '.join(ints)} must be >= 1 (bend_neighbors >= 0, "
                              f"num_nodes >= 2), got {p}")
        for name in ("spring_radius_factor", "bend_radius_factor", "attach_radius", "contact_radius", "reach",
                     "stretch_compliance", "bend_compliance", "grip_compliance", "damping"):
            if not getattr(p, name) > 0:
                raise ConfigError(f"effect physics: {name} must be > 0, got {getattr(p, name)}")
        if p.solver not in ("jacobi", "newton") or p.newton_iterations < 1:
            raise ConfigError(f"effect physics: solver must be 'jacobi' or 'newton' and newton_iterations >= 1, "
                              f"got {p.solver!r}, {p.newton_iterations}")
        if not 0.0 < p.relaxation < 2.0 or not 0.0 < p.gain < 1.0 or not 0.0 < p.grip_threshold < 1.0:
            raise ConfigError("effect physics: relaxation in (0, 2), gain and grip_threshold in (0, 1) required")
        if not p.release_d1 > p.release_d0 >= 0.0:
            raise ConfigError(f"effect physics: release_d1 > release_d0 >= 0 required, got {p.release_d0}, {p.release_d1}")
        if p.bend_model not in ("pairs", "rod"):
            raise ConfigError(f"effect physics: bend_model must be 'pairs' or 'rod', got {p.bend_model!r}")
        if p.bend_model == "rod" and p.solver != "newton":
            raise ConfigError("effect physics: bend_model 'rod' needs solver 'newton'")
        if not p.grip_tilt_compliance >= 0.0 or (p.grip_tilt_compliance > 0.0 and p.solver != "newton"):
            raise ConfigError(f"effect physics: grip_tilt_compliance must be >= 0, and > 0 needs solver 'newton'; "
                              f"got {p.grip_tilt_compliance} with {p.solver!r}")
        if not isinstance(p.carry_velocity, bool):
            raise ConfigError(f"effect physics: carry_velocity must be true or false, got {p.carry_velocity!r}")
        if not 0.0 <= p.friction < 5.0 or p.contact_offset_max < 0:
            raise ConfigError("effect physics: friction in [0, 5) and contact_offset_max >= 0 required")
        f = lambda v: nn.Parameter(torch.tensor(math.log(v)))  # noqa: E731
        self.log_stretch, self.log_bend = f(p.stretch_compliance), f(p.bend_compliance)
        self.log_grip = f(p.grip_compliance)
        if p.grip_tilt_compliance > 0.0:  # only then: checkpoints of models without it load unchanged
            self.log_tilt = f(p.grip_tilt_compliance)
        self.log_damping = f(p.damping)
        self.friction = nn.Parameter(torch.tensor(float(p.friction)))
        self.gain_logit = nn.Parameter(torch.tensor(math.log(p.gain / (1.0 - p.gain))))

    def robot_reach(self) -> float:
        return float(self.params.reach)

    def coefficients(self) -> dict[str, torch.Tensor]:
        out = {"stretch": self.log_stretch.exp(), "bend": self.log_bend.exp(), "grip": self.log_grip.exp(),
               "damping": self.log_damping.exp(), "friction": self.friction}
        if hasattr(self, "log_tilt"):
            out["tilt"] = self.log_tilt.exp()
        return out

    def describe(self) -> dict[str, float]:
        """The physical coefficients as plain numbers (reports)."""
        out = {k: float(v.detach()) for k, v in self.coefficients().items()}
        out["gain"] = float(torch.sigmoid(self.gain_logit.detach()))
        return out

    def layout(self, ctx: EffectContext) -> PhysicsLayout:
        if ctx.rest_positions is None or ctx.cache is None:
            raise RuntimeError("effect physics needs the episode's rest positions and cache (Simulator.effect_context)")
        key = ("physics", id(self))
        lay = ctx.cache.get(key)
        if lay is None:
            lay = build_layout(ctx.rest_positions, ctx.masses, ctx.plane_normal, ctx.plane_offset, self.params)
            ctx.cache[key] = lay
        return lay

    def node_state(self, lay: PhysicsLayout, ctx: EffectContext) -> tuple[torch.Tensor, torch.Tensor]:
        """Node positions and velocities [K, 3]: the mass-weighted means of their cells' splats."""
        m = ctx.masses[:, None]
        K = lay.num_nodes
        x = ctx.positions.new_zeros(K, 3).index_add(0, lay.node_of, m * ctx.positions) / lay.node_mass[:, None]
        v = ctx.positions.new_zeros(K, 3).index_add(0, lay.node_of, m * ctx.velocities) / lay.node_mass[:, None]
        return x, v

    def forward(self, ctx: EffectContext) -> torch.Tensor:
        lay = self.layout(ctx)
        mods = ctx.physics_mods or PhysicsMods()
        x, v = self.node_state(lay, ctx)
        cp1 = ctx.control_points
        robot = cp1 is not None and cp1.shape[0] > 0
        # within reach of a splat (as the trainer's contact frame measures it, soma_ros.training.train.rest_reach)
        near = robot and bool(torch.cdist(cp1.detach(), ctx.positions.detach()).min() < self.params.reach)
        if not near and not bool((v != 0).any()) and not mods.pushes():
            return ctx.positions.new_zeros(ctx.positions.shape)  # at rest stays at rest, exactly
        cp0 = grasp = None
        if robot:
            cp0 = cp1 - float(ctx.dt) * ctx.control_velocities
            if float(ctx.gripper) < self.params.grip_threshold:  # closed: keep the grasp made when it closed
                grasp = (ctx.state_in or {}).get(self.name) or grasp_nodes(lay, x, cp0, self.params,
                                                                             ctx.positions)
        carry = self.params.carry_velocity
        lag_key = self.name + ":lag"  # the state entry of the velocity lag (carry_velocity)
        v0 = v
        if carry:  # start from the end velocity of the prior's last step: v plus the lag it carried
            lag = (ctx.state_in or {}).get(lag_key)
            if lag is not None and tuple(lag.shape) == tuple(v.shape):
                v0 = v + lag.to(v)
        out = pbd_step(lay, x, v0, ctx.gravity, ctx.plane_normal, ctx.plane_offset, float(ctx.dt), self.params,
                       self.coefficients(), cp0, cp1 if robot else None, grasp, mods, return_velocity=carry)
        x1, grasp = out[0], out[1]
        if grasp is not None and ctx.state_out is not None:
            ctx.state_out[self.name] = grasp
        if carry and ctx.state_out is not None:  # the end velocity minus the mean one the splats will have
            ctx.state_out[lag_key] = (out[2] - (x1 - x) / float(ctx.dt)).detach()
        dv = (x1 - x) / float(ctx.dt) - v  # [K, 3] velocity change of every node
        acc = (lay.skin_w[..., None] * dv[lay.skin_idx]).sum(1) * (torch.sigmoid(self.gain_logit) / float(ctx.dt))
        return ctx.masses[:, None] * acc
