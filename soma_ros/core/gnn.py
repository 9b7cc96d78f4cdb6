"""Hierarchical mesh graph network (encode - process - decode), weights shared across levels.

One :class:`HierarchicalGNN` serves every cluster level of the hierarchy (and,
with ``splat_head``, decodes per-splat updates). Per level:

* **encode**: node features [N, 9 + A] and edge features [E, 10] -> latent W
  by MLPs; with ``top_down_latent`` the node encoding adds a linear map of the
  anchor's final latent, so coarse-level context flows down the hierarchy.
* **process**: ``layers`` pre-LayerNorm residual blocks with SiLU MLPs:
  messages m_ij = MLP(e_ij, LN(h)_sender, LN(h)_receiver), node update
  h += MLP(LN(h), mean_j m_ij). With ``edge_updates`` (MeshGraphNets, the
  paper model) edge latents are a residual stream too (e += m, pre-LN).
* **decode**: final LayerNorm then an MLP to :data:`HEAD_OUTPUTS` = 14 numbers
  per node: 3 for the acceleration of the node relative to its anchor, and the
  11 deformation numbers of the SoMA head (two quaternions U, V and three
  log-scales; see :mod:`.simulator`). The last decoder layer has no bias and
  starts scaled by ``out_init_scale`` (0: the output starts at exactly zero, so the
  untrained model is its physical terms alone, bit for bit; the first gradient steps
  move only that layer, the earlier ones follow once it is non-zero).

Where the time goes, and what is done about it (the fine cluster level has
~1,400 nodes and ~23,000 edges at 13k splats; per-edge passes over [E, W]
dominate on a CPU):

* the first message layer is split into three matrices, so the sender and
  receiver terms cost N W^2 (per node) and are then gathered/broadcast;
* without edge updates (the ``cpu`` model) the encoder's last linear layer is
  folded into each block's edge matrix and accumulated by one GEMM straight
  into the gathered sender term, and the message MLP's last linear layer is
  applied after the mean aggregation (a linear map commutes with a mean), so
  the per-edge work of a block is gather, GEMM-accumulate, broadcast add,
  SiLU, reduce;
* static edges use a receiver-major dense layout (:class:`~.graph.DenseTable`):
  the receiver term is a broadcast and the aggregation a reshape-and-sum, no
  scatter;
* under ``torch.no_grad`` the SiLU and the masking run in place (no fresh
  [E, W] buffers: large allocations page-fault on glibc).

Mean (not sum) aggregation keeps message magnitudes comparable across levels
whose degrees differ (the root has no edges, coarse levels few).
"""

from __future__ import annotations

from typing import Optional

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .config import GNNConfig
from .graph import EDGE_FEATURES

__all__ = [
    "HEAD_OUTPUTS",
    "NODE_BASE_FEATURES",
    "node_feature_size",
    "MLP",
    "ProcessorBlock",
    "MessageGraph",
    "HierarchicalGNN",
    "Normalizer",
]

HEAD_OUTPUTS = 14
#: anchor acceleration (3) + external force per mass (3) + velocity relative to the anchor (3)
NODE_BASE_FEATURES = 9


def node_feature_size(attr_dim: int) -> int:
    return NODE_BASE_FEATURES + int(attr_dim)


class MLP(nn.Module):
    """Linear -> SiLU -> (Linear -> SiLU) x (hidden_layers - 1) -> Linear; hidden_layers=0: one Linear.
    ``last_bias=False`` drops the bias of the output layer."""

    def __init__(self, fin: int, hidden: int, fout: int, hidden_layers: int, last_bias: bool = True) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        d = fin
        for _ in range(hidden_layers):
            layers += [nn.Linear(d, hidden), nn.SiLU()]
            d = hidden
        layers.append(nn.Linear(d, fout, bias=last_bias))
        self.net = nn.Sequential(*layers)
        self.fin, self.fout = fin, fout

    @property
    def last(self) -> nn.Linear:
        return self.net[-1]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] != self.fin:
            raise ValueError(f"MLP: expected {self.fin} input features, got {list(x.shape)}")
        return self.net(x)


@dataclass
class MessageGraph:
    """The edges of one level as the blocks use them.

    ``senders`` / ``receivers`` [E]. The first ``num_nodes * dense_k`` edges may
    form a receiver-major dense table (receiver i owns slots [i k, (i+1) k), see
    :class:`~.graph.DenseTable`): there the receiver term is a broadcast and the
    aggregation a reshape-and-sum instead of a gather and a scatter. ``mask``
    [E, 1] is 1.0 for real edges, 0.0 for padding (None: all real).
    ``inv_deg`` [N] = 1 / max(in-degree, 1), ``has_in`` [N] = 1.0 where in-degree > 0.
    """

    senders: torch.Tensor
    receivers: torch.Tensor
    num_nodes: int
    dense_k: int = 0
    mask: Optional[torch.Tensor] = None
    inv_deg: Optional[torch.Tensor] = None
    has_in: Optional[torch.Tensor] = None

    def __post_init__(self) -> None:
        e = self.senders.shape[0]
        if self.receivers.shape != (e,) or self.senders.ndim != 1:
            raise ValueError(f"MessageGraph: senders and receivers must be [E], got {list(self.senders.shape)}, {list(self.receivers.shape)}")
        if self.num_nodes * self.dense_k > e:
            raise ValueError(f"MessageGraph: dense part ({self.num_nodes} x {self.dense_k}) exceeds {e} edges")
        if self.mask is not None and tuple(self.mask.shape) != (e, 1):
            raise ValueError(f"MessageGraph: mask must be [{e}, 1], got {list(self.mask.shape)}")
        if self.inv_deg is None:
            real = self.receivers if self.mask is None else self.receivers[self.mask[:, 0] > 0]
            deg = torch.bincount(real, minlength=self.num_nodes).to(torch.get_default_dtype())
            self.inv_deg = 1.0 / deg.clamp_min(1.0)
            self.has_in = (deg > 0).to(deg.dtype)

    @property
    def num_edges(self) -> int:
        return int(self.senders.shape[0])

    @property
    def num_dense(self) -> int:
        return self.num_nodes * self.dense_k

    def add_receiver_term(self, z: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        """z [E, W] += r[receivers] in place (z must be a fresh tensor)."""
        nd = self.num_dense
        if nd:
            z[:nd].view(self.num_nodes, self.dense_k, -1).add_(r[:, None, :])
        if nd < z.shape[0]:
            z[nd:].add_(r.index_select(0, self.receivers[nd:]))
        return z

    def mean(self, m: torch.Tensor, inplace: bool = False) -> torch.Tensor:
        """Masked mean of edge values m [E, W] per receiver -> [N, W]."""
        if self.mask is not None:
            m = m.mul_(self.mask) if inplace else m * self.mask
        nd = self.num_dense
        if nd:
            agg = m[:nd].view(self.num_nodes, self.dense_k, -1).sum(1)
        else:
            agg = m.new_zeros((self.num_nodes, m.shape[1]))
        if nd < m.shape[0]:
            agg = agg.index_add(0, self.receivers[nd:], m[nd:])
        return agg * self.inv_deg.to(agg.dtype)[:, None]


def _silu(z: torch.Tensor) -> torch.Tensor:
    """SiLU, in place when autograd does not need the input (allocation-free inference)."""
    if torch.is_grad_enabled() and z.requires_grad:
        return F.silu(z)
    return F.silu(z, inplace=True)


class ProcessorBlock(nn.Module):
    """One pre-LN residual message-passing block (see module docstring).

    With ``edge_updates`` (MeshGraphNets): edge latents form a residual stream,
    e += m_ij, and nodes aggregate m_ij. Without (cheaper, the ``cpu`` model):
    edges keep their encoding, messages are recomputed from it and the two
    node latents in every block, and the last linear layer of the message MLP
    is applied after the (linear) mean aggregation -- per node instead of per
    edge, which is exact because a linear map commutes with a mean.
    """

    def __init__(self, width: int, hidden_layers: int, layer_norm: bool, edge_updates: bool = True) -> None:
        super().__init__()
        w = width
        self.edge_updates = bool(edge_updates)
        self.ln_node = nn.LayerNorm(w) if layer_norm else nn.Identity()
        self.ln_edge = nn.LayerNorm(w) if (layer_norm and edge_updates) else nn.Identity()
        self.e_edge = nn.Linear(w, w, bias=False)
        self.e_send = nn.Linear(w, w)  # carries the first layer's bias (per node: cheaper than per edge)
        self.e_recv = nn.Linear(w, w, bias=False)
        self.e_rest = nn.ModuleList(nn.Linear(w, w) for _ in range(hidden_layers))  # each after a SiLU
        self.n_self = nn.Linear(w, w)
        self.n_agg = nn.Linear(w, w, bias=False)
        self.n_rest = nn.ModuleList(nn.Linear(w, w) for _ in range(hidden_layers))

    def forward(
        self,
        h: torch.Tensor,
        e: torch.Tensor,
        graph: MessageGraph,
        e_proj: Optional[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """h [N, W], e [E, W] (edge latents; [E, 0] without edge updates), graph (E edges).
        Without edge updates ``e_proj`` = (x [E, H], M [W, H], c [W]) gives the edge term
        e_edge(encoding) = x M^T + c with the encoder's last layer folded in."""
        hn = self.ln_node(h)
        if graph.num_edges == 0:
            u = self.n_self(hn)
        else:
            if self.edge_updates:
                z = self.e_edge(self.ln_edge(e))
                z.add_(self.e_send(hn).index_select(0, graph.senders))
            else:
                if e_proj is None:
                    raise ValueError("ProcessorBlock: blocks without edge updates need e_proj")
                x, m_w, m_b = e_proj
                # one pass: gather the sender term (with the folded bias), then z += x M^T in the GEMM
                z = (self.e_send(hn) + m_b).index_select(0, graph.senders)
                z.addmm_(x, m_w.t())
            graph.add_receiver_term(z, self.e_recv(hn))
            if self.edge_updates:
                m = z
                for lin in self.e_rest:
                    m = lin(_silu(m))
                e = e + m
                agg = graph.mean(m)
            else:
                for lin in list(self.e_rest)[:-1]:
                    z = lin(_silu(z))
                if len(self.e_rest):
                    z = _silu(z)
                agg = graph.mean(z, inplace=not (torch.is_grad_enabled() and z.requires_grad))
                if len(self.e_rest):
                    last = self.e_rest[-1]
                    agg = agg @ last.weight.t() + last.bias * graph.has_in.to(agg.dtype)[:, None]
            u = self.n_self(hn) + self.n_agg(agg)
        for lin in self.n_rest:
            u = lin(F.silu(u))
        return h + u, e


class HierarchicalGNN(nn.Module):
    """Encoder, ``layers`` processor blocks and decoder shared by all levels."""

    def __init__(self, cfg: GNNConfig) -> None:
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        w, hl = cfg.latent, cfg.mlp_hidden_layers
        self.node_in = node_feature_size(cfg.attr_dim)
        self.node_encoder = MLP(self.node_in, w, w, hl)
        self.edge_encoder = MLP(EDGE_FEATURES, w, w, hl)
        self.top_down = nn.Linear(w, w, bias=False) if cfg.top_down_latent else None
        self.blocks = nn.ModuleList(
            ProcessorBlock(w, hl, cfg.layer_norm, cfg.edge_updates) for _ in range(cfg.layers)
        )

        self.final_norm = nn.LayerNorm(w) if cfg.layer_norm else nn.Identity()
        # No output bias: the simulator subtracts the outputs at the initial state, so a constant
        # output offset would cancel exactly (a parameter that could never learn anything).
        self.decoder = MLP(w, w, HEAD_OUTPUTS, hl, last_bias=False)
        self.splat_head = MLP(2 * w, w, HEAD_OUTPUTS, hl, last_bias=False) if cfg.splat_head else None
        with torch.no_grad():
            for head in (self.decoder, self.splat_head):
                if head is not None:
                    head.last.weight.mul_(cfg.out_init_scale)

    @property
    def width(self) -> int:
        return self.cfg.latent

    def forward_level(
        self,
        node_feats: torch.Tensor,
        graph: MessageGraph,
        edge_feats: torch.Tensor,
        parent_latent: Optional[torch.Tensor] = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One level: node_feats [N, 9+A], graph with E edges, edge_feats [E, 10],
        parent_latent [N, W] or None -> (outputs [N, 14], final latent [N, W])."""
        n = node_feats.shape[0]
        if node_feats.ndim != 2 or node_feats.shape[1] != self.node_in:
            raise ValueError(f"forward_level: node_feats must be [N, {self.node_in}], got {list(node_feats.shape)}")
        if graph.num_nodes != n or tuple(edge_feats.shape) != (graph.num_edges, EDGE_FEATURES):
            raise ValueError(
                f"forward_level: graph of {graph.num_nodes} nodes / {graph.num_edges} edges and edge_feats "
                f"[E, {EDGE_FEATURES}] required for {n} nodes, got edge_feats {list(edge_feats.shape)}"
            )
        h = self.node_encoder(node_feats)
        if self.top_down is not None and parent_latent is not None:
            if parent_latent.shape != (n, self.width):
                raise ValueError(f"forward_level: parent_latent must be [{n}, {self.width}], got {list(parent_latent.shape)}")
            h = h + self.top_down(parent_latent)
        projs: list = [None] * len(self.blocks)
        if graph.num_edges and self.cfg.edge_updates:
            e = self.edge_encoder(edge_feats)
        else:
            e = edge_feats.new_zeros((graph.num_edges, 0))
            if graph.num_edges and len(self.blocks):
                # Fixed edge encodings: the encoder's last (linear) layer is folded into each
                # block's edge term, W_b (W2 x + b2) = (W_b W2) x + W_b b2, so per block the edge
                # term is one GEMM that accumulates into the gathered sender term.
                last = self.edge_encoder.last
                hidden = self.edge_encoder.net[:-1](edge_feats)
                projs = [(hidden, blk.e_edge.weight @ last.weight, blk.e_edge.weight @ last.bias) for blk in self.blocks]
        for blk, pr in zip(self.blocks, projs):
            h, e = blk(h, e, graph, pr)
        lat = self.final_norm(h)
        out = self.decoder(lat)
        assert out.shape == (n, HEAD_OUTPUTS)
        return out, lat

    def forward_splats(self, node_feats: torch.Tensor, parent_latent: torch.Tensor) -> torch.Tensor:
        """Per-splat head: node_feats [N0, 9+A], anchor latent [N0, W] -> outputs [N0, 14]."""
        if self.splat_head is None:
            raise RuntimeError("forward_splats: this model has no splat head (gnn.splat_head: false)")
        if node_feats.shape != (parent_latent.shape[0], self.node_in) or parent_latent.shape[1] != self.width:
            raise ValueError(
                f"forward_splats: node_feats [N, {self.node_in}] and parent_latent [N, {self.width}] required, "
                f"got {list(node_feats.shape)} and {list(parent_latent.shape)}"
            )
        h = self.node_encoder(node_feats)
        return self.splat_head(torch.cat([h, parent_latent], dim=-1))


class Normalizer(nn.Module):
    """Feature standardiser (x - mean) / std with running statistics.

    ``fit=False``: identity (mean 0, std 1) unless statistics were loaded.
    ``fit=True``: in training mode, every call accumulates the rows it sees
    (float64 sums) until ``max_count`` rows, then the statistics freeze. The
    statistics are buffers, so checkpoints carry them.
    """

    def __init__(self, size: int, fit: bool = False, max_count: int = 1_000_000, eps: float = 1e-6) -> None:
        super().__init__()
        self.size = int(size)
        self.fit = bool(fit)
        self.max_count = int(max_count)
        self.eps = float(eps)
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("sum", torch.zeros(self.size, dtype=torch.float64))
        self.register_buffer("sumsq", torch.zeros(self.size, dtype=torch.float64))
        self._n = 0.0  # host copy of ``count`` (no device sync per call)

    def _load_from_state_dict(self, *args, **kwargs):  # keep the host copy in step with loaded buffers
        super()._load_from_state_dict(*args, **kwargs)
        self._n = float(self.count)

    @property
    def accumulating(self) -> bool:
        return self.fit and self.training and self._n < self.max_count

    def stats(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean [size], std [size]) in float64."""
        if self._n == 0:
            return torch.zeros_like(self.sum), torch.ones_like(self.sum)
        mean = self.sum / self.count
        var = (self.sumsq / self.count - mean * mean).clamp_min(0.0)
        return mean, var.sqrt().clamp_min(self.eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] != self.size:
            raise ValueError(f"Normalizer: expected {self.size} features, got {list(x.shape)}")
        if self.accumulating and x.shape[0] > 0:
            xd = x.detach().reshape(-1, self.size).to(torch.float64)
            self.count += xd.shape[0]
            self._n += xd.shape[0]
            self.sum += xd.sum(0)
            self.sumsq += (xd * xd).sum(0)
        if self._n == 0:
            return x
        mean, std = self.stats()
        return (x - mean.to(x.dtype)) / std.to(x.dtype)

    def extra_repr(self) -> str:
        return f"size={self.size}, fit={self.fit}, count={int(self.count)}"
