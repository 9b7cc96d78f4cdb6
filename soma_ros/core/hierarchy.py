"""The splat hierarchy: distance-threshold clustering, built once per object.

Levels
------
Level 0 holds the N splats; level i (1 <= i <= len(thresholds)) holds the
clusters of level i-1 at distance threshold ``thresholds[i-1]`` (SoMA: 0.02 m
then 0.2 m); the last level is a single root node, the anchor of the top
cluster level. ``parents[l]`` ([N_l] long) maps every node of level l to its
cluster at level l+1.

Aggregation (SoMA, Preliminaries): a cluster's mass is the sum of its
children's masses, its position their mass-weighted mean and its attributes
their plain mean. Applied recursively, a cluster's position is also the
mass-weighted mean of all the splats below it.

Clustering guarantee
--------------------
:func:`complete_linkage_clusters` partitions the nodes of one level so that

1. **diameter**: any two members of a cluster are at most ``threshold`` apart
   (complete linkage at that distance). Consequently every member lies within
   ``threshold`` of the cluster's mass-weighted mean, which is in the members'
   convex hull;
2. **maximality**: no two clusters can be merged without breaking 1 (the
   complete-linkage distance of every pair of clusters exceeds the threshold),
   so the partition is not needlessly fine.

Algorithm (N = 13,000 splats: about a second, see tests): (a) seeds by a
greedy ball cover, sweeping the points in voxel order, with balls of radius
``seed_fraction * threshold`` (<= threshold / 2, so a seed alone has diameter
<= threshold); (b) exact complete-linkage agglomeration of the seeds: the
linkage of two seeds is the largest distance between their members, computed
exactly for every pair of seeds whose centres are within the threshold (no
other pair can ever link, since a linkage is at least the distance of the two
seed centres, which are members); merges go smallest-linkage first and update
linkages with the Lance-Williams rule D(A u B, C) = max(D(A, C), D(B, C)); it
stops when no pair links at <= threshold. The result is exact complete
linkage restricted to unions of seeds.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch
from scipy.spatial import cKDTree

__all__ = [
    "Hierarchy",
    "build_hierarchy",
    "complete_linkage_clusters",
    "scatter_sum",
    "scatter_mean",
    "mass_weighted_mean",
]


# ----------------------------------------------------------------------------- scatter helpers
def scatter_sum(values: torch.Tensor, index: torch.Tensor, size: int) -> torch.Tensor:
    """out[j] = sum of values[i] with index[i] == j. values [N, ...], index [N] long -> [size, ...]."""
    if values.shape[0] != index.shape[0]:
        raise ValueError(f"scatter_sum: {values.shape[0]} values for {index.shape[0]} indices")
    out = values.new_zeros((size,) + tuple(values.shape[1:]))
    return out.index_add_(0, index, values)


def scatter_mean(values: torch.Tensor, index: torch.Tensor, size: int) -> torch.Tensor:
    """Plain mean per group (0 for an empty group)."""
    s = scatter_sum(values, index, size)
    cnt = scatter_sum(torch.ones_like(index, dtype=values.dtype), index, size).clamp_min(1.0)
    return s / cnt.reshape((size,) + (1,) * (values.ndim - 1))


def mass_weighted_mean(values: torch.Tensor, masses: torch.Tensor, index: torch.Tensor, size: int) -> torch.Tensor:
    """sum(m_i v_i) / sum(m_i) per group; a group of total mass 0 falls back to the plain mean."""
    msum = scatter_sum(masses, index, size)
    wsum = scatter_sum(values * masses.reshape((-1,) + (1,) * (values.ndim - 1)), index, size)
    plain = scatter_mean(values, index, size)
    ok = (msum > 0).reshape((size,) + (1,) * (values.ndim - 1))
    return torch.where(ok, wsum / msum.clamp_min(torch.finfo(values.dtype).tiny).reshape(ok.shape), plain)


# ----------------------------------------------------------------------------- clustering
def _ball_cover_seeds(points: np.ndarray, radius: float) -> np.ndarray:
    """Greedy ball cover: label [N] of the seed ball each point belongs to.

    Points are visited in voxel (cell = radius) order; an unassigned point
    becomes a seed and takes every unassigned point within ``radius``.
    """
    n = points.shape[0]
    cells = np.floor((points - points.min(0)) / radius).astype(np.int64)
    order = np.lexsort((points[:, 2], points[:, 1], points[:, 0], cells[:, 2], cells[:, 1], cells[:, 0]))
    tree = cKDTree(points)
    label = np.full(n, -1, dtype=np.int64)
    nseed = 0
    for i in order:
        if label[i] >= 0:
            continue
        nb = np.asarray(tree.query_ball_point(points[i], radius), dtype=np.int64)
        nb = nb[label[nb] < 0]
        label[nb] = nseed
        label[i] = nseed
        nseed += 1
    return label


def _pair_max_distances(points: np.ndarray, groups: list[np.ndarray], pairs: np.ndarray) -> np.ndarray:
    """Largest member-to-member distance for every pair of groups ([P, 2] indices) -> [P]."""
    if len(pairs) == 0:
        return np.zeros(0)
    sizes = np.array([len(g) for g in groups])
    mmax = int(sizes.max())
    # Pad every group by repeating its first member: repeats do not change a max distance.
    padded = np.empty((len(groups), mmax, 3))
    for gi, g in enumerate(groups):
        padded[gi] = points[np.resize(g, mmax)]
    out = np.empty(len(pairs))
    # Bucket pairs by the power-of-two ceilings of their two group sizes, so that each
    # bucket is padded only to its own largest groups (sizes vary a lot across a cloud).
    ca = np.ceil(np.log2(sizes[pairs[:, 0]])).astype(np.int64)
    cb = np.ceil(np.log2(sizes[pairs[:, 1]])).astype(np.int64)
    bucket = ca * 64 + cb
    for key in np.unique(bucket):
        idx_all = np.nonzero(bucket == key)[0]
        ma = min(mmax, 1 << int(key // 64))
        mb = min(mmax, 1 << int(key % 64))
        chunk = max(1, 2_000_000 // (ma * mb))
        for s in range(0, len(idx_all), chunk):
            idx = idx_all[s : s + chunk]
            a = padded[pairs[idx, 0], :ma]  # [P, ma, 3]
            b = padded[pairs[idx, 1], :mb]
            d2 = np.zeros((len(idx), ma, mb))
            for c in range(3):
                d2 += (a[:, :, None, c] - b[:, None, :, c]) ** 2
            out[idx] = np.sqrt(d2.reshape(len(idx), -1).max(axis=1))
    return out


def complete_linkage_clusters(points: np.ndarray, threshold: float, seed_fraction: float = 0.25) -> np.ndarray:
    """Cluster labels [N] (0..K-1) with complete-linkage diameter <= ``threshold``.

    See the module docstring for the guarantee and the algorithm. Labels are
    numbered in order of each cluster's smallest member index (deterministic).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"complete_linkage_clusters: points must be [N, 3], got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("complete_linkage_clusters: points contain non-finite values")
    if not threshold > 0:
        raise ValueError(f"complete_linkage_clusters: threshold must be > 0, got {threshold}")
    if not 0 < seed_fraction <= 0.5:
        raise ValueError(f"complete_linkage_clusters: seed_fraction must lie in (0, 0.5], got {seed_fraction}")
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    seed_label = _ball_cover_seeds(points, seed_fraction * threshold)
    nseed = int(seed_label.max()) + 1
    order = np.argsort(seed_label, kind="stable")
    bounds = np.searchsorted(seed_label[order], np.arange(nseed + 1))
    groups = [order[bounds[i] : bounds[i + 1]] for i in range(nseed)]
    # seed centre = its first (seeding) member is not tracked; any member works for the pruning
    # bound, since the linkage of two seeds is >= the distance of any two of their members.
    centres = points[[g[0] for g in groups]]
    cand = cKDTree(centres).query_pairs(threshold, output_type="ndarray")
    dist = _pair_max_distances(points, groups, cand)
    keep = dist <= threshold
    cand, dist = cand[keep], dist[keep]

    nbr: list[dict[int, float]] = [dict() for _ in range(nseed)]
    heap: list[tuple[float, int, int]] = []
    for (a, b), d in zip(cand.tolist(), dist.tolist()):
        nbr[a][b] = d
        nbr[b][a] = d
        heap.append((d, a, b))
    heapq.heapify(heap)
    alive = np.ones(nseed, dtype=bool)
    owner = np.arange(nseed)  # seed -> surviving cluster id (path-compressed below)
    while heap:
        d, a, b = heapq.heappop(heap)
        if not (alive[a] and alive[b]) or nbr[a].get(b) != d:
            continue  # stale entry
        # merge b into a; Lance-Williams for complete linkage: D(a u b, c) = max(D(a,c), D(b,c)),
        # and a pair absent from the dicts has linkage > threshold.
        na, nb = nbr[a], nbr[b]
        del na[b]
        del nb[a]
        for c in list(na.keys() | nb.keys()):
            dc = max(na.get(c, np.inf), nb.get(c, np.inf))
            nc = nbr[c]
            nc.pop(b, None)
            if dc <= threshold:
                na[c] = dc
                nc[a] = dc
                heapq.heappush(heap, (dc, min(a, c), max(a, c)))
            else:
                na.pop(c, None)
                nc.pop(a, None)
        nbr[b] = {}
        alive[b] = False
        owner[b] = a
    # resolve owners (chains b -> a -> ...)
    root = owner.copy()
    for i in range(nseed):
        r = i
        while root[r] != r:
            r = root[r]
        root[i] = r
    lab = root[seed_label]
    # renumber by smallest member index
    first = np.full(nseed, n, dtype=np.int64)
    np.minimum.at(first, lab, np.arange(n))
    uniq = np.unique(lab)
    rank = np.empty(nseed, dtype=np.int64)
    rank[uniq[np.argsort(first[uniq], kind="stable")]] = np.arange(len(uniq))
    return rank[lab]


# ----------------------------------------------------------------------------- hierarchy
@dataclass
class Hierarchy:
    """Cluster tree over the splats (see module docstring).

    ==================  ==========================  =====================================
    field               shape                       meaning
    ==================  ==========================  =====================================
    thresholds          list[float] (L - 1)         complete-linkage diameters, m
    parents             list of [N_l] long, l<L     cluster index at level l + 1
    rest_positions      list of [N_l, 3], l<=L      positions when built (mass-weighted)
    masses              list of [N_l]               kg (sums)
    ==================  ==========================  =====================================

    L = ``num_levels - 1`` is the root level (one node).
    """

    thresholds: list[float]
    parents: list[torch.Tensor]
    rest_positions: list[torch.Tensor]
    masses: list[torch.Tensor]
    seed_fraction: float = 0.25

    def __post_init__(self) -> None:
        nl = len(self.rest_positions)
        if len(self.parents) != nl - 1 or len(self.masses) != nl or len(self.thresholds) != nl - 2:
            raise ValueError(
                f"Hierarchy: inconsistent level counts (positions {nl}, parents {len(self.parents)}, "
                f"masses {len(self.masses)}, thresholds {len(self.thresholds)})"
            )
        if self.rest_positions[-1].shape[0] != 1:
            raise ValueError("Hierarchy: the last level must be a single root node")
        for l in range(nl):
            x = self.rest_positions[l]
            if x.ndim != 2 or x.shape[1] != 3 or tuple(self.masses[l].shape) != (x.shape[0],):
                raise ValueError(f"Hierarchy: level {l} positions must be [N,3] and masses [N]")
            if l < nl - 1:
                p = self.parents[l]
                if p.dtype != torch.long or tuple(p.shape) != (x.shape[0],):
                    raise ValueError(f"Hierarchy: parents[{l}] must be long [{x.shape[0]}]")
                n_up = self.rest_positions[l + 1].shape[0]
                if x.shape[0] and (int(p.min()) < 0 or int(p.max()) >= n_up):
                    raise ValueError(f"Hierarchy: parents[{l}] out of range [0, {n_up})")
                if torch.bincount(p, minlength=n_up).min() == 0:
                    raise ValueError(f"Hierarchy: level {l + 1} has a cluster without children")

    # ------------------------------------------------------------------ queries
    @property
    def num_levels(self) -> int:
        """Levels including splats (0) and root (last)."""
        return len(self.rest_positions)

    @property
    def root_level(self) -> int:
        return self.num_levels - 1

    @property
    def sizes(self) -> list[int]:
        return [int(x.shape[0]) for x in self.rest_positions]

    @property
    def device(self) -> torch.device:
        return self.rest_positions[0].device

    def to(self, device=None, dtype=None) -> "Hierarchy":
        return Hierarchy(
            thresholds=list(self.thresholds),
            parents=[p.to(device) for p in self.parents],
            rest_positions=[x.to(device=device, dtype=dtype) for x in self.rest_positions],
            masses=[m.to(device=device, dtype=dtype) for m in self.masses],
            seed_fraction=self.seed_fraction,
        )

    def offsets(self, rest_positions: Optional[Sequence[torch.Tensor]] = None) -> list[torch.Tensor]:
        """Per level l < L: [N_l, 3] offsets X_child - X_anchor to the parent (rest shape;
        this hierarchy's rest positions unless others are given)."""
        xs = self.rest_positions if rest_positions is None else list(rest_positions)
        return [xs[l] - xs[l + 1].index_select(0, self.parents[l]) for l in range(self.root_level)]

    def splat_ancestor(self, level: int) -> torch.Tensor:
        """[N_0] index of every splat's ancestor at ``level``."""
        idx = torch.arange(self.sizes[0], device=self.device)
        for l in range(level):
            idx = self.parents[l][idx]
        return idx

    # ------------------------------------------------------------ aggregation
    def aggregate_sum(self, values: torch.Tensor, from_level: int = 0) -> list[torch.Tensor]:
        """Sums up the tree: [values at from_level, at from_level+1, ..., at root]."""
        self._check_level_values(values, from_level)
        out = [values]
        for l in range(from_level, self.root_level):
            out.append(scatter_sum(out[-1], self.parents[l], self.sizes[l + 1]))
        return out

    def aggregate_mean(self, values: torch.Tensor, from_level: int = 0) -> list[torch.Tensor]:
        """Plain means of the children, level by level (SoMA's attribute rule)."""
        self._check_level_values(values, from_level)
        out = [values]
        for l in range(from_level, self.root_level):
            out.append(scatter_mean(out[-1], self.parents[l], self.sizes[l + 1]))
        return out

    def aggregate_positions(self, positions: torch.Tensor, masses: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """(positions per level, masses per level) from splat positions [N0,3] and masses [N0]."""
        self._check_level_values(positions, 0)
        if tuple(masses.shape) != (self.sizes[0],):
            raise ValueError(f"aggregate_positions: masses must be [{self.sizes[0]}], got {list(masses.shape)}")
        xs, ms = [positions], [masses]
        for l in range(self.root_level):
            xs.append(mass_weighted_mean(xs[-1], ms[-1], self.parents[l], self.sizes[l + 1]))
            ms.append(scatter_sum(ms[-1], self.parents[l], self.sizes[l + 1]))
        return xs, ms

    def _check_level_values(self, values: torch.Tensor, level: int) -> None:
        if values.shape[0] != self.sizes[level]:
            raise ValueError(
                f"Hierarchy: level {level} has {self.sizes[level]} nodes, got values of shape {list(values.shape)}"
            )

    # ------------------------------------------------------------ serialisation
    def to_dict(self) -> dict:
        """Plain dict of tensors/lists/floats (safe for ``torch.load(weights_only=True)``)."""
        return {
            "format": "soma_ros.hierarchy/1",
            "thresholds": [float(t) for t in self.thresholds],
            "seed_fraction": float(self.seed_fraction),
            "parents": [p.detach().cpu().clone() for p in self.parents],
            "rest_positions": [x.detach().cpu().clone() for x in self.rest_positions],
            "masses": [m.detach().cpu().clone() for m in self.masses],
        }

    @staticmethod
    def from_dict(d: dict) -> "Hierarchy":
        if d.get("format") != "soma_ros.hierarchy/1":
            raise ValueError(f"Hierarchy.from_dict: unknown format {d.get('format')!r}")
        return Hierarchy(
            thresholds=list(d["thresholds"]),
            parents=list(d["parents"]),
            rest_positions=list(d["rest_positions"]),
            masses=list(d["masses"]),
            seed_fraction=float(d["seed_fraction"]),
        )


def build_hierarchy(
    positions: torch.Tensor,
    masses: torch.Tensor,
    thresholds: Sequence[float] = (0.02, 0.2),
    seed_fraction: float = 0.25,
) -> Hierarchy:
    """Cluster splat positions [N,3] (masses [N]) level by level, then add a root.

    Level i+1 clusters the (mass-weighted) positions of level i with
    ``thresholds[i]``; see :func:`complete_linkage_clusters`.
    """
    if positions.ndim != 2 or positions.shape[1] != 3 or positions.shape[0] == 0:
        raise ValueError(f"build_hierarchy: positions must be [N>0, 3], got {list(positions.shape)}")
    if tuple(masses.shape) != (positions.shape[0],):
        raise ValueError(f"build_hierarchy: masses must be [{positions.shape[0]}], got {list(masses.shape)}")
    if (masses < 0).any() or not torch.isfinite(masses).all():
        raise ValueError("build_hierarchy: masses must be finite and >= 0")
    thr = [float(t) for t in thresholds]
    if not thr or any(b <= a for a, b in zip([0.0] + thr[:-1], thr)):
        raise ValueError(f"build_hierarchy: thresholds must be > 0 and increasing, got {thr}")
    x = positions.detach()
    m = masses.detach().to(x.dtype)
    xs, ms, parents = [x], [m], []
    for t in thr:
        lab = torch.from_numpy(complete_linkage_clusters(xs[-1].cpu().numpy(), t, seed_fraction)).to(x.device)
        k = int(lab.max()) + 1
        parents.append(lab)
        xs.append(mass_weighted_mean(xs[-1], ms[-1], lab, k))
        ms.append(scatter_sum(ms[-1], lab, k))
    root = torch.zeros(xs[-1].shape[0], dtype=torch.long, device=x.device)
    parents.append(root)
    xs.append(mass_weighted_mean(xs[-1], ms[-1], root, 1))
    ms.append(scatter_sum(ms[-1], root, 1))
    return Hierarchy(thresholds=thr, parents=parents, rest_positions=xs, masses=ms, seed_fraction=seed_fraction)
