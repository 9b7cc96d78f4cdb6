"""The hierarchical GNN: fast paths equal the plain message-passing maths; normalisers."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from soma_ros.core.config import GNNConfig
from soma_ros.core.gnn import HEAD_OUTPUTS, HierarchicalGNN, MessageGraph, Normalizer
from soma_ros.core.graph import EDGE_FEATURES, DenseTable, knn_radius_edges

torch.set_num_threads(1)


def _graph(n=120, k=6, radius=0.05, seed=0):
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(n, 3, generator=g) * 0.2
    return knn_radius_edges(pos, k, radius)  # irregular in-degrees (radius filter)


def _naive_level(gnn: HierarchicalGNN, nodes, edges, efeat, parent):
    """Plain per-edge message passing written out (the no-edge-update block, hidden_layers=1)."""
    n = nodes.shape[0]
    s, r = edges
    h = gnn.node_encoder(nodes) + gnn.top_down(parent)
    enc = gnn.edge_encoder(efeat)
    deg = torch.bincount(r, minlength=n).float()
    for blk in gnn.blocks:
        hn = blk.ln_node(h)
        z = blk.e_edge(enc) + blk.e_send(hn)[s] + blk.e_recv(hn)[r]
        m = blk.e_rest[0](F.silu(z))  # message computed per edge
        agg = torch.zeros(n, m.shape[1]).index_add_(0, r, m) / deg.clamp_min(1)[:, None]
        u = blk.n_self(hn) + blk.n_agg(agg)
        h = h + blk.n_rest[0](F.silu(u))
    return gnn.decoder(gnn.final_norm(h))


@pytest.mark.parametrize("edge_updates", [False, True])
def test_dense_layout_and_inplace_inference_match_plain_edges(edge_updates):
    torch.manual_seed(0)
    gnn = HierarchicalGNN(GNNConfig(latent=16, layers=3, edge_updates=edge_updates, out_init_scale=1.0))
    edges = _graph()
    n = 120
    nodes = torch.randn(n, 14)
    efeat = torch.randn(edges.shape[1], EDGE_FEATURES)
    parent = torch.randn(n, 16)
    plain = MessageGraph(edges[0], edges[1], n)
    out_plain, lat_plain = gnn.forward_level(nodes, plain, efeat, parent)
    dense = DenseTable.build(edges, n, max_padding=10.0)
    assert dense is not None and dense.mask is not None  # irregular: padding present
    ef_pad = efeat.new_zeros((n * dense.k, EDGE_FEATURES)).index_copy(0, dense.slots, efeat)
    dg = MessageGraph(dense.senders, dense.receivers, n, dense.k, dense.mask)
    out_dense, _ = gnn.forward_level(nodes, dg, ef_pad, parent)
    assert torch.allclose(out_dense, out_plain, atol=1e-5)
    with torch.no_grad():  # in-place (allocation-free) inference path
        out_ng, _ = gnn.forward_level(nodes, dg, ef_pad, parent)
    assert torch.allclose(out_ng, out_plain, atol=1e-5)
    if not edge_updates:  # last message layer applied after the mean == per-edge maths
        assert torch.allclose(out_plain, _naive_level(gnn, nodes, edges, efeat, parent), atol=1e-5)
    assert out_plain.shape == (n, HEAD_OUTPUTS) and lat_plain.shape == (n, 16)


def test_levels_without_edges_and_shape_errors():
    gnn = HierarchicalGNN(GNNConfig(latent=8, layers=2, edge_updates=False))
    empty = torch.zeros(2, 0, dtype=torch.long)
    out, lat = gnn.forward_level(torch.randn(1, 14), MessageGraph(empty[0], empty[1], 1), torch.zeros(0, EDGE_FEATURES))
    assert out.shape == (1, HEAD_OUTPUTS) and torch.isfinite(out).all()
    with pytest.raises(ValueError, match="node_feats"):
        gnn.forward_level(torch.randn(3, 13), MessageGraph(empty[0], empty[1], 3), torch.zeros(0, EDGE_FEATURES))
    with pytest.raises(ValueError, match="edge_feats"):
        gnn.forward_level(torch.randn(3, 14), MessageGraph(empty[0], empty[1], 3), torch.zeros(2, EDGE_FEATURES))
    with pytest.raises(RuntimeError, match="splat head"):
        gnn.forward_splats(torch.randn(3, 14), torch.randn(3, 8))


def test_dense_table_layout():
    edges = torch.tensor([[1, 2, 0, 3], [0, 0, 1, 2]])  # receivers 0:2, 1:1, 2:1, 3:0
    t = DenseTable.build(edges, 4, max_padding=10.0)
    assert t.k == 2
    assert torch.equal(t.senders[t.slots], edges[0]) and torch.equal(t.receivers[t.slots], edges[1])
    assert t.mask.flatten().tolist() == [1.0, 1.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    assert DenseTable.build(edges, 4, max_padding=0.25) is None  # too much padding
    full = torch.tensor([[1, 0], [0, 1]])
    assert DenseTable.build(full, 2).mask is None


def test_normalizer_statistics_fit_and_freeze():
    norm = Normalizer(3, fit=True, max_count=1000)
    norm.train()
    g = torch.Generator().manual_seed(0)
    x = torch.randn(600, 3, generator=g) * torch.tensor([1.0, 2.0, 0.5]) + torch.tensor([3.0, -1.0, 0.0])
    norm(x[:300])
    y = norm(x[300:])
    mean, std = norm.stats()
    assert torch.allclose(mean.float(), x.mean(0), atol=1e-5)
    assert torch.allclose(std.float(), x.std(0, unbiased=False), atol=1e-5)
    assert torch.allclose(y, (x[300:] - x.mean(0)) / x.std(0, unbiased=False), atol=1e-4)
    norm(torch.randn(600, 3))  # reaches max_count: stops after this batch
    c = float(norm.count)
    norm(torch.randn(10, 3))
    assert float(norm.count) == c == 1200
    fresh = Normalizer(3)
    fresh.load_state_dict(norm.state_dict())
    assert torch.equal(fresh(x), norm(x))
    ident = Normalizer(3)
    assert torch.equal(ident(x), x)  # no statistics: identity
    with pytest.raises(ValueError, match="3 features"):
        ident(torch.zeros(2, 4))
