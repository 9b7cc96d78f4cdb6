"""Per-level graphs of the hierarchy: static (rest-shape) and dynamic (current-shape) edges.

Edges are directed ``[2, E]`` long tensors, row 0 = senders, row 1 =
receivers. A node receives from its k nearest neighbours that lie within the
level's radius (kNN filtered by radius, k = 16 by default), so every in-degree
is at most k.

* **Static edges** are built once from the rest positions of each level
  (``GraphConfig.radii``); they are the material topology and survive any
  deformation. They are stored with the hierarchy (:class:`LevelGraphs`,
  serialisable with :meth:`LevelGraphs.to_dict`).
* **Dynamic edges** are the kNN-within-radius pairs of the *current* shape
  that are not static edges (new contacts, e.g. a folded cloth touching
  itself, in the spirit of MeshGraphNets' world edges). The simulator
  recomputes them every ``GraphConfig.dynamic_every`` steps and reuses them in
  between; at the rest shape they are empty (current kNN = rest kNN).

Edge features (:func:`edge_features`, ``EDGE_FEATURES`` = 10 per edge):
unit direction (3), length / rest length (1), relative velocity / v_scale
(3), cos and sin of the angle between the current and the rest edge vector
(2), edge type (0 static, 1 dynamic).

kNN runs on detached positions: scipy's cKDTree for CPU tensors, a chunked
``torch.cdist`` + ``topk`` on CUDA (or when asked). Index tensors carry no
gradient; the features do.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch
from scipy.spatial import cKDTree

__all__ = [
    "EDGE_FEATURES",
    "knn_radius_edges",
    "edge_keys",
    "remove_edges",
    "dynamic_edges",
    "edge_features",
    "LevelGraphs",
    "DenseTable",
    "build_static_graphs",
    "safe_norm",
]

EDGE_FEATURES = 10


def safe_norm(x: torch.Tensor, dim: int = -1, keepdim: bool = False, eps: float = 1e-9) -> torch.Tensor:
    """sqrt(|x|^2 + eps^2): smooth at 0 (finite gradient), within eps of |x|."""
    return torch.sqrt((x * x).sum(dim=dim, keepdim=keepdim) + eps * eps)


def _empty_edges(device) -> torch.Tensor:
    return torch.zeros((2, 0), dtype=torch.long, device=device)


def knn_radius_edges(pos: torch.Tensor, k: int, radius: float, backend: str = "auto") -> torch.Tensor:
    """Edges [2, E] (senders, receivers): each node receives from its <= k nearest
    other nodes within ``radius`` (inclusive). Sorted by receiver, then distance.

    pos: [N, 3]. backend: "auto" (scipy on CPU, torch on CUDA), "scipy", "torch".
    """
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"knn_radius_edges: pos must be [N, 3], got {list(pos.shape)}")
    if k < 1 or not radius > 0:
        raise ValueError(f"knn_radius_edges: k >= 1 and radius > 0 required, got k={k} radius={radius}")
    n = pos.shape[0]
    device = pos.device
    if n < 2:
        return _empty_edges(device)
    kk = min(k + 1, n)
    if backend == "auto":
        backend = "torch" if pos.is_cuda else "scipy"
    if backend == "scipy":
        p = pos.detach().cpu().double().numpy()
        d, j = cKDTree(p).query(p, k=kk)
        d = d.reshape(n, kk)
        j = j.reshape(n, kk)
        i = np.broadcast_to(np.arange(n)[:, None], j.shape)
        ok = (j != i) & (d <= radius)
        # keep at most k per receiver (the query may return k+1 non-self hits with duplicates)
        ok &= np.cumsum(ok, axis=1) <= k
        send = torch.from_numpy(j[ok].astype(np.int64))
        recv = torch.from_numpy(i[ok].astype(np.int64))
        return torch.stack([send, recv]).to(device)
    if backend != "torch":
        raise ValueError(f"knn_radius_edges: unknown backend {backend!r} (auto, scipy, torch)")
    p = pos.detach()
    sends, recvs = [], []
    chunk = max(1, 2_000_000 // n)
    ar = torch.arange(n, device=device)
    for s in range(0, n, chunk):
        q = p[s : s + chunk]
        d = torch.cdist(q, p)  # [c, n]
        d[torch.arange(q.shape[0], device=device), ar[s : s + chunk]] = float("inf")
        dv, j = torch.topk(d, kk - 1, dim=1, largest=False, sorted=True)  # kk - 1 = min(k, n - 1) >= 1
        ok = dv <= radius
        i = ar[s : s + chunk, None].expand_as(j)
        sends.append(j[ok])
        recvs.append(i[ok])
    return torch.stack([torch.cat(sends), torch.cat(recvs)])


def edge_keys(edges: torch.Tensor, n: int) -> torch.Tensor:
    """Unique int64 key receiver * n + sender per edge [E]."""
    return edges[1] * n + edges[0]


#: up to this many nodes a level keeps a dense [N*N] bool table of its static edges (<= 16 MB)
DENSE_LOOKUP_MAX_NODES = 4096


def remove_edges(
    edges: torch.Tensor, sorted_keys: torch.Tensor, n: int, dense: Optional[torch.Tensor] = None
) -> torch.Tensor:
    """Drop the edges whose key is in ``sorted_keys`` (ascending int64); ``dense`` [n*n] bool,
    True at the keys, is an equivalent faster lookup."""
    if edges.shape[1] == 0 or sorted_keys.numel() == 0:
        return edges
    keys = edge_keys(edges, n)
    if dense is not None:
        present = dense.index_select(0, keys)
    else:
        pos = torch.searchsorted(sorted_keys, keys).clamp_max(sorted_keys.numel() - 1)
        present = sorted_keys[pos] == keys
    return edges[:, ~present]


def dynamic_edges(
    pos: torch.Tensor,
    k: int,
    radius: float,
    static_sorted_keys: torch.Tensor,
    backend: str = "auto",
    dense: Optional[torch.Tensor] = None,
) -> torch.Tensor:
    """Current-shape kNN-within-radius edges that are not static edges. pos [N,3] -> [2, E]."""
    e = knn_radius_edges(pos, k, radius, backend)
    return remove_edges(e, static_sorted_keys, pos.shape[0], dense)


def edge_features(
    pos: torch.Tensor,
    vel: torch.Tensor,
    rest_pos: torch.Tensor,
    edges: torch.Tensor,
    edge_type: float,
    velocity_scale: float,
    rest_vectors: Optional[torch.Tensor] = None,
) -> torch.Tensor:
    """Edge features [E, 10] (see module docstring) from positions/velocities/rest positions [N, 3].

    ``rest_vectors`` [E, 3] = rest_pos[senders] - rest_pos[receivers] may be passed precomputed.
    """
    if not (pos.shape == vel.shape == rest_pos.shape) or pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(
            f"edge_features: pos, vel, rest_pos must all be [N, 3]; got {list(pos.shape)}, "
            f"{list(vel.shape)}, {list(rest_pos.shape)}"
        )
    if edges.ndim != 2 or edges.shape[0] != 2:
        raise ValueError(f"edge_features: edges must be [2, E], got {list(edges.shape)}")
    s, r = edges[0], edges[1]
    u = pos.index_select(0, s) - pos.index_select(0, r)
    if rest_vectors is None:
        u0 = rest_pos.index_select(0, s) - rest_pos.index_select(0, r)
    else:
        if tuple(rest_vectors.shape) != (edges.shape[1], 3):
            raise ValueError(f"edge_features: rest_vectors must be [{edges.shape[1]}, 3], got {list(rest_vectors.shape)}")
        u0 = rest_vectors
    length = safe_norm(u, keepdim=True)
    rest_len = safe_norm(u0, keepdim=True).clamp_min(1e-6)
    dvel = (vel.index_select(0, s) - vel.index_select(0, r)) / velocity_scale
    denom = length * rest_len
    cos = (u * u0).sum(-1, keepdim=True) / denom
    sin = safe_norm(torch.linalg.cross(u, u0), keepdim=True) / denom
    kind = u.new_full((u.shape[0], 1), float(edge_type))
    out = torch.cat([u / length, length / rest_len, dvel, cos, sin, kind], dim=-1)
    assert out.shape == (edges.shape[1], EDGE_FEATURES)
    return out


@dataclass
class DenseTable:
    """A receiver-major padded copy of an edge list: receiver i owns slots [i k, (i+1) k).

    ``senders`` / ``receivers`` [N k] (padding slots are self loops), ``mask`` [N k, 1]
    (1.0 real edge, 0.0 padding; None when there is no padding), ``slots`` [E] the slot
    of each original edge. With this
    layout a message-passing layer needs no scatter for aggregation and no gather for the
    receiver term (a reshape to [N, k, W] and a broadcast), see :mod:`.gnn`.
    """

    k: int
    senders: torch.Tensor
    receivers: torch.Tensor
    mask: Optional[torch.Tensor]
    slots: torch.Tensor

    @staticmethod
    def build(edges: torch.Tensor, n: int, max_padding: float = 0.25) -> Optional["DenseTable"]:
        """Padded table of ``edges`` [2, E] over ``n`` receivers, or None when it would be
        more than ``max_padding`` padding (or there are no edges)."""
        e = edges.shape[1]
        if e == 0 or n == 0:
            return None
        recv = edges[1]
        counts = torch.bincount(recv, minlength=n)
        k = int(counts.max())
        if n * k > e * (1.0 + max_padding):
            return None
        order = torch.argsort(recv, stable=True)
        start = torch.cumsum(counts, 0) - counts
        rank = torch.arange(e, device=edges.device) - start[recv[order]]
        slots = torch.empty(e, dtype=torch.long, device=edges.device)
        slots[order] = recv[order] * k + rank
        senders = torch.arange(n, device=edges.device).repeat_interleave(k)  # padding: self loops
        senders[slots] = edges[0]
        mask = torch.zeros(n * k, 1, device=edges.device)
        mask[slots] = 1.0
        receivers = torch.arange(n, device=edges.device).repeat_interleave(k)
        return DenseTable(k, senders, receivers, None if n * k == e else mask, slots)

    @property
    def edges(self) -> torch.Tensor:
        return torch.stack([self.senders, self.receivers])


@dataclass
class LevelGraphs:
    """Static edges per level ([2, E_l] long; level 0 and the root may be empty),
    their sorted keys and lookup tables (for excluding them from dynamic edges), and
    padded receiver-major copies (:class:`DenseTable`, None where too irregular)."""

    static: list[torch.Tensor]
    sizes: list[int]

    def __post_init__(self) -> None:
        if len(self.static) != len(self.sizes):
            raise ValueError("LevelGraphs: one edge tensor per level required")
        for l, (e, n) in enumerate(zip(self.static, self.sizes)):
            if e.ndim != 2 or e.shape[0] != 2 or e.dtype != torch.long:
                raise ValueError(f"LevelGraphs: level {l} edges must be long [2, E], got {e.dtype} {list(e.shape)}")
            if e.numel() and (int(e.min()) < 0 or int(e.max()) >= n):
                raise ValueError(f"LevelGraphs: level {l} edge index out of range [0, {n})")
        self.static_keys = [torch.sort(edge_keys(e, n)).values for e, n in zip(self.static, self.sizes)]
        self.static_lookup: list[Optional[torch.Tensor]] = []
        for keys, n in zip(self.static_keys, self.sizes):
            if n <= DENSE_LOOKUP_MAX_NODES:
                table = torch.zeros(n * n, dtype=torch.bool, device=keys.device)
                table[keys] = True
                self.static_lookup.append(table)
            else:
                self.static_lookup.append(None)
        self.dense: list[Optional[DenseTable]] = [DenseTable.build(e, n) for e, n in zip(self.static, self.sizes)]
        self.static_degree = [torch.bincount(e[1], minlength=n) for e, n in zip(self.static, self.sizes)]

    def to(self, device) -> "LevelGraphs":
        return LevelGraphs([e.to(device) for e in self.static], list(self.sizes))

    def to_dict(self) -> dict:
        return {
            "format": "soma_ros.level_graphs/1",
            "static": [e.detach().cpu().clone() for e in self.static],
            "sizes": [int(n) for n in self.sizes],
        }

    @staticmethod
    def from_dict(d: dict) -> "LevelGraphs":
        if d.get("format") != "soma_ros.level_graphs/1":
            raise ValueError(f"LevelGraphs.from_dict: unknown format {d.get('format')!r}")
        return LevelGraphs(list(d["static"]), [int(n) for n in d["sizes"]])


def build_static_graphs(
    rest_positions: Sequence[torch.Tensor],
    k: int,
    radii: Sequence[float],
    levels: Optional[Sequence[int]] = None,
    backend: str = "auto",
) -> LevelGraphs:
    """Static kNN-within-radius edges at the rest positions of each level in ``levels``
    (default: every level except the splats); other levels get no edges."""
    nl = len(rest_positions)
    if len(radii) != nl:
        raise ValueError(f"build_static_graphs: {len(radii)} radii for {nl} levels")
    levels = list(range(1, nl)) if levels is None else list(levels)
    out = []
    for l, x in enumerate(rest_positions):
        if l in levels:
            out.append(knn_radius_edges(x, k, float(radii[l]), backend))
        else:
            out.append(_empty_edges(x.device))
    return LevelGraphs(out, [int(x.shape[0]) for x in rest_positions])
