"""Per-level graphs: kNN filtered by radius, static vs dynamic edges, edge features."""

from __future__ import annotations

import pytest
import torch

from soma_ros.core.graph import (
    EDGE_FEATURES,
    LevelGraphs,
    build_static_graphs,
    dynamic_edges,
    edge_features,
    edge_keys,
    knn_radius_edges,
)
from soma_ros.core.hierarchy import build_hierarchy
from soma_ros.core.scenes import synthetic_rope

torch.set_num_threads(1)


def _brute(pos: torch.Tensor, k: int, radius: float) -> set[tuple[int, int]]:
    d = torch.cdist(pos.double(), pos.double())
    d.fill_diagonal_(float("inf"))
    out = set()
    for i in range(pos.shape[0]):
        vals, idx = torch.sort(d[i])
        for v, j in zip(vals[:k].tolist(), idx[:k].tolist()):
            if v <= radius:
                out.add((j, i))
    return out


@pytest.mark.parametrize("backend", ["scipy", "torch"])
def test_knn_radius_matches_brute_force(backend):
    g = torch.Generator().manual_seed(0)
    pos = torch.rand(300, 3, generator=g) * 0.2
    k, radius = 8, 0.035
    e = knn_radius_edges(pos, k, radius, backend)
    assert e.dtype == torch.long and e.shape[0] == 2
    got = set(zip(e[0].tolist(), e[1].tolist()))
    assert got == _brute(pos, k, radius)
    # radius filter, no self loops, in-degree <= k
    lengths = (pos[e[0]] - pos[e[1]]).norm(dim=-1)
    assert float(lengths.max()) <= radius + 1e-7
    assert bool((e[0] != e[1]).all())
    assert int(torch.bincount(e[1], minlength=300).max()) <= k
    # the radius really filters: some nodes have fewer than k neighbours
    assert int(torch.bincount(e[1], minlength=300).min()) < k


def test_knn_edge_cases():
    assert knn_radius_edges(torch.zeros(1, 3), 4, 1.0).shape == (2, 0)
    e = knn_radius_edges(torch.zeros(3, 3), 4, 1.0)  # coincident points: no self loops, all pairs
    assert set(zip(e[0].tolist(), e[1].tolist())) == {(i, j) for i in range(3) for j in range(3) if i != j}
    with pytest.raises(ValueError):
        knn_radius_edges(torch.zeros(3, 2), 4, 1.0)
    with pytest.raises(ValueError, match="backend"):
        knn_radius_edges(torch.zeros(3, 3), 4, 1.0, backend="faiss")


def test_static_graphs_per_level_radius_and_serialisation():
    sp = synthetic_rope(2000, seed=1)
    h = build_hierarchy(sp.means, sp.mass, [0.02, 0.2])
    radii = [0.03, 0.05, 0.15, 5.0]
    gr = build_static_graphs(h.rest_positions, 16, radii)
    assert gr.static[0].shape[1] == 0  # splat level not built by default
    assert gr.static[-1].shape[1] == 0  # a single root has no neighbours
    for l in (1, 2):
        e = gr.static[l]
        x = h.rest_positions[l]
        assert e.shape[1] > 0
        assert float((x[e[0]] - x[e[1]]).norm(dim=-1).max()) <= radii[l] + 1e-6
    d = LevelGraphs.from_dict(gr.to_dict())
    assert all(torch.equal(a, b) for a, b in zip(d.static, gr.static)) and d.sizes == gr.sizes
    with pytest.raises(ValueError, match="out of range"):
        LevelGraphs([torch.tensor([[0], [5]])], [3])


def test_dynamic_edges_are_new_contacts_only():
    g = torch.Generator().manual_seed(2)
    rest = torch.rand(200, 3, generator=g) * torch.tensor([0.5, 0.5, 0.01])
    gr = build_static_graphs([rest, rest[:1]], 8, [0.05, 1.0], levels=[0])
    keys, dense = gr.static_keys[0], gr.static_lookup[0]
    # at the rest shape there is nothing new
    assert dynamic_edges(rest, 8, 0.05, keys).shape[1] == 0
    assert dynamic_edges(rest, 8, 0.05, keys, dense=dense).shape[1] == 0
    # fold: move the right half onto the left half -> contacts between far-apart nodes
    cur = rest.clone()
    right = cur[:, 0] > 0.25
    cur[right, 0] = 0.5 - cur[right, 0]
    cur[right, 2] += 0.005
    dyn = dynamic_edges(cur, 8, 0.05, keys)
    assert dyn.shape[1] > 0
    assert torch.equal(dyn, dynamic_edges(cur, 8, 0.05, keys, dense=dense))
    static_set = set(edge_keys(gr.static[0], 200).tolist())
    assert not (set(edge_keys(dyn, 200).tolist()) & static_set)
    assert float((cur[dyn[0]] - cur[dyn[1]]).norm(dim=-1).max()) <= 0.05 + 1e-7


def test_edge_features_values():
    rest = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    pos = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.2, 0.0]])  # stretched x2 and rotated by 90 degrees
    vel = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5]])
    e = torch.tensor([[1], [0]])
    f = edge_features(pos, vel, rest, e, 1.0, velocity_scale=0.25)
    assert f.shape == (1, EDGE_FEATURES)
    exp = torch.tensor([[0.0, 1.0, 0.0, 2.0, 0.0, 0.0, 2.0, 0.0, 1.0, 1.0]])
    assert torch.allclose(f, exp, atol=1e-6)
    # at rest: length ratio 1, angle 0, finite gradients even for a zero-length edge
    f0 = edge_features(rest, torch.zeros_like(rest), rest, e, 0.0, 1.0)
    assert torch.allclose(f0[0, 3:9], torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]), atol=1e-6)
    p = torch.zeros(2, 3, requires_grad=True)
    edge_features(p, torch.zeros(2, 3), torch.zeros(2, 3), e, 0.0, 1.0).sum().backward()
    assert torch.isfinite(p.grad).all()
