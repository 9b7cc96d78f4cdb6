"""A PhysTwin-style spring-mass baseline over the splats, with the gripper attached by springs.

The physics baseline of the evaluation (issue #6), in the spirit of PhysTwin
(a spring-mass model of the object whose few physical parameters are fitted
by gradient to the observations) but written from scratch, pure torch, CPU.

Model
-----
* **Nodes.** ``num_nodes`` mass points chosen among the initial splat means by
  farthest-point sampling (deterministic: the first is the splat nearest the
  centroid). Each node carries ``total mass / num_nodes``.
* **Springs.** Every node is joined to its ``neighbors`` nearest nodes within
  ``spring_radius_factor`` x the median nearest-node spacing (symmetric, no
  duplicates); rest lengths are the initial distances. Force on node i from
  spring (i, j), per unit mass: ``k * (l - l0) / l0 * e + c * ((v_j - v_i).e) e``
  with ``e`` the unit vector i -> j (strain stiffness k [m/s^2], dashpot c [1/s]).
* **Gravity, drag** ``-drag * v``, and the **table**: a node may not go below
  its initial height above the table plane, capped at ``contact_offset_max``
  (nodes resting on the table stay supported where they were reconstructed);
  a node pushed below is projected back, its normal velocity clipped to >= 0
  and its tangential velocity reduced by Coulomb friction ``mu |dv_n|``.
* **Gripper** (the robot action R_t: control points [P, 3] and gripper state c
  in [0, 1], 0 = closed). While ``c < grip_threshold`` the nodes that were
  within ``attach_radius`` of the control points' centroid when it closed are
  attached by springs (stiffness ``grip_k`` [1/s^2], damping ratio 0.5) to
  their nearest control point, at the offset they had at attach time; opening
  releases them. The nearest control point also pushes a node closer than
  ``contact_radius`` out (penalty ``grip_k``). Control points move linearly within a frame.
* **Integration.** Symplectic Euler with ``substeps`` steps per frame. The
  stiffnesses are parameterised as ``bound * sigmoid(theta)`` with the bound the
  explicit-integration stability limit of the episode's springs, so any value
  the optimiser reaches is stable (springs, dashpots, grip and contact together).
* **Splats** follow the nodes by linear blend skinning: each splat is bound to
  its ``carry_neighbors`` nearest nodes (weights ~ 1/d^2) and moves as
  ``sum_k w_k (x_k + R_k (X - X_k))``; ``R_k`` is the rotation of the node's
  spring neighbourhood (polar decomposition of its deformation, regularised
  toward identity for degenerate, e.g. collinear, neighbourhoods). Covariances
  are rotated by the blended rotation. ``rotations=False`` (used while fitting)
  skips R (translation-only blend, no SVD in the gradient).

Fitted parameters (:attr:`SpringMass.parameter_names`): stiffness, dashpot,
drag, grip stiffness, table friction -- five numbers shared by all episodes of
an object, fitted by :func:`soma_ros.evaluation.baselines.fit_spring_mass` on the training
bags' depth (PhysTwin fits to observed 3D points; here the points are the
back-projected depth of the object pixels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
from torch import nn

from .config import from_dict, to_dict

__all__ = ["SpringMassConfig", "SpringMassEpisode", "SpringMass", "farthest_point_sampling", "neighbour_pairs",
           "skin_weights"]


@dataclass
class SpringMassConfig:
    """Topology, integration and initial physical parameters (see module docstring)."""

    num_nodes: int = 150
    neighbors: int = 8
    spring_radius_factor: float = 3.0
    substeps: int = 40
    carry_neighbors: int = 4
    total_mass: float = 0.1
    contact_offset_max: float = 0.02
    attach_radius: float = 0.02
    contact_radius: float = 0.006
    grip_threshold: float = 0.5
    rotation_regularizer: float = 1e-2
    # initial values as fractions of the stability bound (stiffnesses) or plain values
    stiffness_fraction: float = 0.5
    dashpot_fraction: float = 0.2
    drag: float = 1.0
    grip_fraction: float = 0.5
    friction: float = 0.5

    def validate(self) -> "SpringMassConfig":
        if self.num_nodes < 2 or self.neighbors < 1 or self.substeps < 1 or self.carry_neighbors < 1:
            raise ValueError("SpringMassConfig: num_nodes >= 2, neighbors >= 1, substeps >= 1, carry_neighbors >= 1")
        for name in ("stiffness_fraction", "dashpot_fraction", "grip_fraction"):
            v = getattr(self, name)
            if not 0.0 < v < 1.0:
                raise ValueError(f"SpringMassConfig.{name} must lie in (0, 1), got {v}")
        for name in ("spring_radius_factor", "total_mass", "attach_radius", "contact_radius", "drag"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SpringMassConfig.{name} must be > 0")
        if not 0.0 < self.friction < 5.0 or not 0.0 < self.grip_threshold < 1.0:
            raise ValueError("SpringMassConfig: friction in (0, 5), grip_threshold in (0, 1)")
        if self.contact_offset_max < 0:
            raise ValueError("SpringMassConfig.contact_offset_max must be >= 0")
        return self


def farthest_point_sampling(points: torch.Tensor, k: int) -> torch.Tensor:
    """Indices [k] of a farthest-point sample of points [N, 3], starting at the point nearest the centroid."""
    n = points.shape[0]
    if n == 0:
        raise ValueError("farthest_point_sampling: no points")
    k = min(k, n)
    p = points.detach().to(torch.float64)
    first = int(torch.argmin((p - p.mean(0)).norm(dim=-1)))
    idx = torch.empty(k, dtype=torch.long)
    idx[0] = first
    dist = (p - p[first]).norm(dim=-1)
    for i in range(1, k):
        j = int(torch.argmax(dist))
        idx[i] = j
        dist = torch.minimum(dist, (p - p[j]).norm(dim=-1))
    return idx


def neighbour_pairs(d: torch.Tensor, k: int, radius: float, skip: int = 0) -> torch.Tensor:
    """[2, E] node pairs (i < j, unique): each node and its nearest ``k`` nodes beyond the first
    ``skip``, within ``radius`` (d: [K, K] distances, inf on the diagonal). With ``skip`` 0 every
    node keeps at least its nearest neighbour."""
    K = d.shape[0]
    kk = min(skip + k, K - 1)
    if kk <= skip:
        return torch.zeros(2, 0, dtype=torch.long)
    nd, nj = d.topk(kk, dim=1, largest=False)
    nd, nj = nd[:, skip:], nj[:, skip:]
    ok = nd <= radius
    if skip == 0:
        ok[:, 0] = True
    ii = torch.arange(K)[:, None].expand_as(nj)
    a, b = ii[ok], nj[ok]
    return torch.unique(torch.stack([torch.minimum(a, b), torch.maximum(a, b)]), dim=1)


def skin_weights(points: torch.Tensor, nodes: torch.Tensor, k: int,
                 spacing: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Linear-blend skinning of points [N, 3] to their ``k`` nearest nodes [K, 3]: (indices [N, k],
    weights [N, k], rows sum to 1, inverse-square distance softened by a quarter node spacing)."""
    cd, ci = torch.cdist(points, nodes).topk(min(k, nodes.shape[0]), dim=1, largest=False)
    w = 1.0 / (cd + 0.25 * spacing).square()
    return ci, w / w.sum(dim=1, keepdim=True)


def _logit(x: float) -> float:
    return math.log(x / (1.0 - x))


@dataclass
class SpringMassEpisode:
    """Constants of one episode: nodes, springs, skinning, table, stability bounds.

    rest [K, 3] node rest positions; springs [2, E] (i < j); rest_len [E]; neighbors [K, n] node
    neighbour lists for rotations (-1 padded) ; carry_idx / carry_w [N, k] splat skinning;
    splat_rest [N, 3]; splat_covs [N, 3, 3]; floor [K] minimum signed distance to the table;
    k_max / c_max / grip_max: stability bounds (1/s^2 per unit strain x l0, 1/s, 1/s^2).
    """

    rest: torch.Tensor
    springs: torch.Tensor
    rest_len: torch.Tensor
    neighbors: torch.Tensor
    carry_idx: torch.Tensor
    carry_w: torch.Tensor
    splat_rest: torch.Tensor
    splat_covs: torch.Tensor
    floor: torch.Tensor
    gravity: torch.Tensor
    plane_normal: torch.Tensor
    plane_offset: float
    dt: float
    k_max: float
    c_max: float
    grip_max: float

    @property
    def num_nodes(self) -> int:
        return int(self.rest.shape[0])


class SpringMass(nn.Module):
    """Spring-mass simulator with five fitted parameters (see module docstring).

    Usage::

        sm = SpringMass(SpringMassConfig(total_mass=0.05))
        ep = sm.init_episode(splats, scene)           # scene: core.simulator.SceneContext
        nodes = sm.rollout(ep, actions)               # [T, K, 3], actions[t] moves frame t-1 -> t
        means, covs = sm.carry(ep, nodes[t])          # splats at frame t
    """

    parameter_names = ("stiffness", "dashpot", "drag", "grip", "friction")

    def __init__(self, config: Optional[SpringMassConfig] = None) -> None:
        super().__init__()
        self.config = (config or SpringMassConfig()).validate()
        c = self.config
        self.theta_stiffness = nn.Parameter(torch.tensor(_logit(c.stiffness_fraction)))
        self.theta_dashpot = nn.Parameter(torch.tensor(_logit(c.dashpot_fraction)))
        self.log_drag = nn.Parameter(torch.tensor(math.log(c.drag)))
        self.theta_grip = nn.Parameter(torch.tensor(_logit(c.grip_fraction)))
        self.theta_friction = nn.Parameter(torch.tensor(_logit(c.friction / 5.0)))

    # ------------------------------------------------------------------ parameters
    def physical(self, ep: SpringMassEpisode) -> dict[str, torch.Tensor]:
        """The physical parameters for an episode's stability bounds (differentiable)."""
        return {
            "stiffness": ep.k_max * torch.sigmoid(self.theta_stiffness),
            "dashpot": ep.c_max * torch.sigmoid(self.theta_dashpot),
            "drag": self.log_drag.exp(),
            "grip": ep.grip_max * torch.sigmoid(self.theta_grip),
            "friction": 5.0 * torch.sigmoid(self.theta_friction),
        }

    def describe(self) -> dict[str, float]:
        """Fitted parameters as plain numbers (stiffnesses as fractions of the stability bound)."""
        with torch.no_grad():
            return self._describe()

    def _describe(self) -> dict[str, float]:
        return {
            "stiffness_fraction": float(torch.sigmoid(self.theta_stiffness)),
            "dashpot_fraction": float(torch.sigmoid(self.theta_dashpot)),
            "drag_per_s": float(self.log_drag.exp()),
            "grip_fraction": float(torch.sigmoid(self.theta_grip)),
            "friction": float(5.0 * torch.sigmoid(self.theta_friction)),
        }

    # ------------------------------------------------------------------ set-up
    def init_episode(self, splats, scene) -> SpringMassEpisode:
        """Nodes, springs and skinning for an episode starting from ``splats`` in ``scene``
        (:class:`~soma_ros.core.simulator.SceneContext`: gravity, table plane, dt)."""
        c = self.config
        with torch.no_grad():
            means = splats.means.detach().to(torch.float32).cpu()
            n = means.shape[0]
            if n < 2:
                raise ValueError(f"SpringMass.init_episode: need >= 2 splats, got {n}")
            idx = farthest_point_sampling(means, c.num_nodes)
            rest = means[idx].clone()
            K = rest.shape[0]
            d = torch.cdist(rest, rest)
            d.fill_diagonal_(math.inf)
            spacing = float(d.min(dim=1).values.median())
            pairs = neighbour_pairs(d, c.neighbors, c.spring_radius_factor * max(spacing, 1e-6))
            rest_len = (rest[pairs[0]] - rest[pairs[1]]).norm(dim=-1).clamp_min(1e-6)
            # neighbour lists (for node rotations)
            deg = torch.bincount(pairs.reshape(-1), minlength=K)
            maxdeg = int(deg.max())
            nbr = torch.full((K, maxdeg), -1, dtype=torch.long)
            fill = torch.zeros(K, dtype=torch.long)
            for s, t in pairs.t().tolist():
                nbr[s, fill[s]] = t
                fill[s] += 1
                nbr[t, fill[t]] = s
                fill[t] += 1
            # splat skinning
            ci, w = skin_weights(means, rest, c.carry_neighbors, spacing)
            # table floor
            nrm = scene.plane_normal.detach().to(torch.float32).cpu()
            off = float(scene.plane_offset)
            sd = rest @ nrm + off
            floor = sd.clamp(min=0.0, max=c.contact_offset_max)
            # stability bounds of symplectic Euler with step h: for a node, h^2 (sum of stiffness
            # rates) + 2 h (sum of damping rates) < 4. Budget: springs 0.4 and gripper 2 x 0.2 of
            # (1.4 / h)^2; dashpots 0.4 / h; the gripper's damping (ratio 0.5) 0.63 / h.
            h = float(scene.dt) / c.substeps
            deg_max = float(deg.max())
            l_min = float(rest_len.min())
            omega2 = (1.4 / h) ** 2
            # spring term: per unit mass, k / l0 per spring, both ends moving, deg springs per node
            k_max = 0.4 * omega2 * l_min / (2.0 * deg_max)
            c_max = 0.4 / (h * 2.0 * deg_max)
            grip_max = 0.2 * omega2
            covs = splats.covariances().detach().to(torch.float32).cpu()
        return SpringMassEpisode(
            rest=rest, springs=pairs, rest_len=rest_len, neighbors=nbr, carry_idx=ci, carry_w=w,
            splat_rest=means.clone(), splat_covs=covs, floor=floor,
            gravity=scene.gravity.detach().to(torch.float32).cpu(), plane_normal=nrm, plane_offset=off,
            dt=float(scene.dt), k_max=k_max, c_max=c_max, grip_max=grip_max,
        )

    # ------------------------------------------------------------------ dynamics
    def rollout(self, ep: SpringMassEpisode, actions: Sequence, progress=None) -> torch.Tensor:
        """Node positions of every frame [T, K, 3]: frame 0 is the rest state; ``actions[t]``
        (a :class:`~soma_ros.core.simulator.RobotAction` or None) is the robot at frame t, so
        ``actions[0]`` only sets where the robot starts. Differentiable w.r.t. the parameters."""
        c = self.config
        p = self.physical(ep)
        k, cdash, drag, kg, mu = p["stiffness"], p["dashpot"], p["drag"], p["grip"], p["friction"]
        h = ep.dt / c.substeps
        drag = drag.clamp(max=0.2 / h)
        x = ep.rest.clone()
        v = torch.zeros_like(x)
        i, j = ep.springs
        K = x.shape[0]
        n = ep.plane_normal
        g = ep.gravity
        out = [x]
        attached: Optional[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = None  # (nodes, cp index, offset)
        prev_cp = None
        for t in range(1, len(actions)):
            a = actions[t]
            cp = None if a is None else a.control_points.detach().to(torch.float32).cpu()
            grip = 1.0 if a is None else float(a.gripper)
            if cp is not None and prev_cp is None:
                prev_cp = cp
            if cp is not None and prev_cp is not None and prev_cp.shape != cp.shape:
                prev_cp = cp
            # attach / release (decided once per frame, at the frame's gripper state)
            if cp is None or grip >= c.grip_threshold:
                attached = None
            elif attached is None:
                xd = x.detach()
                centre = cp.mean(0)
                near = torch.nonzero((xd - centre).norm(dim=-1) <= c.attach_radius).reshape(-1)
                if near.numel() > 0:
                    dcp = torch.cdist(xd[near], cp)
                    jn = dcp.argmin(dim=1)
                    attached = (near, jn, xd[near] - cp[jn])
            for s in range(c.substeps):
                f = torch.zeros_like(x)
                # springs
                dx = x[j] - x[i]
                length = dx.norm(dim=-1, keepdim=True).clamp_min(1e-9)
                e = dx / length
                strain = (length[:, 0] - ep.rest_len) / ep.rest_len
                dv = ((v[j] - v[i]) * e).sum(-1)
                fs = (k * strain + cdash * dv)[:, None] * e
                f = f.index_add(0, i, fs).index_add(0, j, -fs)
                f = f + g - drag * v
                if cp is not None:
                    w = (s + 1) / c.substeps
                    cps = prev_cp + w * (cp - prev_cp)
                    cpv = (cp - prev_cp) / ep.dt
                    if attached is not None:
                        nodes, jn, offs = attached
                        target = cps[jn] + offs
                        fa = kg * (target - x[nodes]) + kg.sqrt() * (cpv[jn] - v[nodes])
                        f = f.index_add(0, nodes, fa)
                    # contact push from the nearest control point (one contact per node keeps it stable)
                    dc = x[:, None, :] - cps[None, :, :]
                    dist = dc.norm(dim=-1)
                    dmin, jmin = dist.min(dim=1)
                    pen = (c.contact_radius - dmin).clamp_min(0.0)
                    if bool((pen > 0).any()):
                        dirn = (x - cps[jmin]) / dmin.clamp_min(1e-9)[:, None]
                        f = f + kg * pen[:, None] * dirn
                v = v + h * f
                x = x + h * v
                # table: stay above the floor, friction on the tangential velocity
                sd = x @ n + ep.plane_offset
                below = (ep.floor - sd).clamp_min(0.0)
                if bool((below > 0).any()):
                    x = x + below[:, None] * n
                    vn = v @ n
                    dvn = (-vn).clamp_min(0.0) * (below > 0).to(v.dtype)
                    v = v + dvn[:, None] * n
                    vt = v - (v @ n)[:, None] * n
                    vt_norm = vt.norm(dim=-1).clamp_min(1e-9)
                    scale = (1.0 - mu * dvn / vt_norm).clamp_min(0.0)
                    v = v - vt + vt * scale[:, None]
            prev_cp = cp
            out.append(x)
            if progress is not None:
                progress.update(1)
        nodes = torch.stack(out)
        assert nodes.shape == (len(actions) if actions else 1, K, 3) or not actions
        return nodes

    # ------------------------------------------------------------------ splats
    def node_rotations(self, ep: SpringMassEpisode, x: torch.Tensor) -> torch.Tensor:
        """Rotation of every node's spring neighbourhood [K, 3, 3] (regularised polar decomposition)."""
        nbr = ep.neighbors
        valid = (nbr >= 0).to(x.dtype)[..., None]
        idx = nbr.clamp_min(0)
        D = (ep.rest[idx] - ep.rest[:, None, :]) * valid  # [K, n, 3]
        d = (x[idx] - x[:, None, :]) * valid
        A = torch.einsum("kni,knj->kij", d, D)
        scale = (D * D).sum(dim=(1, 2)).clamp_min(1e-12) / 3.0
        A = A + self.config.rotation_regularizer * scale[:, None, None] * torch.eye(3, dtype=x.dtype)
        U, _, Vh = torch.linalg.svd(A.double())
        det = torch.det(U @ Vh)
        S = torch.ones_like(U[..., 0])
        S[:, 2] = det.sign()
        R = (U * S[:, None, :]) @ Vh
        return R.to(x.dtype)

    def carry(self, ep: SpringMassEpisode, x: torch.Tensor, rotations: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Splat means [N, 3] and covariances [N, 3, 3] for node positions x [K, 3]."""
        if x.shape != ep.rest.shape:
            raise ValueError(f"carry: nodes must be {list(ep.rest.shape)}, got {list(x.shape)}")
        ci, w = ep.carry_idx, ep.carry_w
        off = ep.splat_rest[:, None, :] - ep.rest[ci]  # [N, k, 3]
        if not rotations:
            means = (w[..., None] * (x[ci] + off)).sum(1)
            return means, ep.splat_covs
        R = self.node_rotations(ep, x)
        means = (w[..., None] * (x[ci] + torch.einsum("nkij,nkj->nki", R[ci], off))).sum(1)
        Rb = R[ci[:, 0]]
        covs = Rb @ ep.splat_covs @ Rb.transpose(-1, -2)
        return means, covs

    # ------------------------------------------------------------------ persistence
    def to_payload(self, extra: Optional[dict] = None) -> dict:
        return {
            "format": "soma_ros.spring_mass/1",
            "config": to_dict(self.config),
            "state_dict": {k: v.detach().cpu().clone() for k, v in self.state_dict().items()},
            "extra": dict(extra or {}),
        }

    @staticmethod
    def from_payload(payload: dict) -> "SpringMass":
        if not isinstance(payload, dict) or payload.get("format") != "soma_ros.spring_mass/1":
            raise ValueError("not a soma_ros spring-mass checkpoint")
        cfg = from_dict(SpringMassConfig, payload["config"], "spring_mass.")
        sm = SpringMass(cfg)
        sm.load_state_dict(payload["state_dict"])
        return sm
