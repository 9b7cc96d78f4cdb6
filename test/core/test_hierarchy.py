"""The splat hierarchy: clustering guarantee, maximality, aggregation, serialisation."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch

from soma_ros.core.hierarchy import (
    Hierarchy,
    build_hierarchy,
    complete_linkage_clusters,
    mass_weighted_mean,
    scatter_mean,
    scatter_sum,
)
from soma_ros.core.scenes import synthetic_rope

torch.set_num_threads(1)


def _clouds():
    rng = np.random.default_rng(0)
    blob = rng.normal(scale=0.03, size=(400, 3))
    sheet = np.c_[rng.uniform(-0.1, 0.1, (400, 2)), rng.uniform(0, 0.002, 400)]
    line = np.c_[np.linspace(0, 0.3, 300), rng.normal(scale=0.002, size=(300, 2))]
    grid = np.stack(np.meshgrid(*[np.arange(6) * 0.01] * 3), -1).reshape(-1, 3)  # ties everywhere
    dup = np.repeat(rng.uniform(0, 0.05, (50, 3)), 3, axis=0)  # coincident points
    return {"blob": blob, "sheet": sheet, "line": line, "grid": grid, "dup": dup}


def _pairwise(x: np.ndarray) -> np.ndarray:
    return np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(-1))


@pytest.mark.parametrize("name", ["blob", "sheet", "line", "grid", "dup"])
@pytest.mark.parametrize("threshold", [0.015, 0.04])
def test_complete_linkage_guarantee_and_maximality(name, threshold):
    pts = _clouds()[name]
    lab = complete_linkage_clusters(pts, threshold)
    assert lab.shape == (len(pts),) and lab.min() == 0
    k = lab.max() + 1
    assert set(np.unique(lab)) == set(range(k))  # contiguous labels
    d = _pairwise(pts)
    same = lab[:, None] == lab[None, :]
    # 1. diameter: any two members of a cluster are within the threshold
    assert d[same].max() <= threshold + 1e-12
    # 2. maximality: every pair of clusters has complete-linkage distance > threshold
    link = np.full((k, k), -np.inf)
    np.maximum.at(link, (lab[:, None].repeat(len(pts), 1), lab[None, :].repeat(len(pts), 0)), d)
    off = ~np.eye(k, dtype=bool)
    assert (link[off] > threshold).all()
    # not trivially fine: clusters really merge
    assert k < len(pts) / 2


def test_complete_linkage_is_deterministic_and_validates():
    pts = _clouds()["blob"]
    assert np.array_equal(complete_linkage_clusters(pts, 0.03), complete_linkage_clusters(pts.copy(), 0.03))
    with pytest.raises(ValueError, match="threshold"):
        complete_linkage_clusters(pts, 0.0)
    with pytest.raises(ValueError, match="seed_fraction"):
        complete_linkage_clusters(pts, 0.03, seed_fraction=0.6)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        complete_linkage_clusters(pts[:, :2], 0.03)
    with pytest.raises(ValueError, match="non-finite"):
        complete_linkage_clusters(np.full((3, 3), np.nan), 0.03)
    assert complete_linkage_clusters(np.zeros((1, 3)), 0.03).tolist() == [0]


def test_scatter_helpers():
    v = torch.tensor([[1.0], [2.0], [3.0], [4.0]])
    idx = torch.tensor([0, 0, 2, 2])
    assert scatter_sum(v, idx, 3).flatten().tolist() == [3.0, 0.0, 7.0]
    assert scatter_mean(v, idx, 3).flatten().tolist() == [1.5, 0.0, 3.5]
    m = torch.tensor([1.0, 3.0, 0.0, 0.0])  # group 2 has zero mass -> plain mean
    assert mass_weighted_mean(v, m, idx, 3).flatten().tolist() == [1.75, 0.0, 3.5]


@pytest.fixture(scope="module")
def rope_hierarchy():
    sp = synthetic_rope(3000, seed=5)
    g = torch.Generator().manual_seed(1)
    mass = torch.rand(3000, generator=g) + 0.1  # non-uniform masses
    return sp, mass, build_hierarchy(sp.means, mass, [0.02, 0.2])


def test_hierarchy_structure_and_per_level_guarantee(rope_hierarchy):
    sp, mass, h = rope_hierarchy
    assert h.num_levels == 4 and h.root_level == 3
    assert h.sizes[0] == 3000 and h.sizes[-1] == 1
    assert h.sizes[0] > h.sizes[1] > h.sizes[2] >= 1
    for l, t in enumerate(h.thresholds):
        x = h.rest_positions[l].double()
        p = h.parents[l]
        for c in range(h.sizes[l + 1]):
            members = x[p == c]
            assert len(members) >= 1
            diam = torch.cdist(members, members).max()
            assert diam <= t + 1e-6, (l, c, float(diam))
            # consequence: every member within t of the cluster's (mass-weighted) position
            assert (members - h.rest_positions[l + 1][c].double()).norm(dim=-1).max() <= t + 1e-6
    assert bool((h.parents[-1] == 0).all())


def test_hierarchy_aggregation(rope_hierarchy):
    sp, mass, h = rope_hierarchy
    # masses are sums, totals preserved
    for l in range(h.root_level):
        assert torch.allclose(scatter_sum(h.masses[l], h.parents[l], h.sizes[l + 1]), h.masses[l + 1])
    assert math.isclose(float(h.masses[-1]), float(mass.sum()), rel_tol=1e-5)
    # positions are mass-weighted means of the children, and of all splats below
    for l in range(1, h.num_levels):
        anc = h.splat_ancestor(l)
        w = scatter_sum(sp.means * mass[:, None], anc, h.sizes[l]) / scatter_sum(mass, anc, h.sizes[l])[:, None]
        assert torch.allclose(h.rest_positions[l], w, atol=1e-6)
    xs, ms = h.aggregate_positions(sp.means, mass)
    for a, b in zip(xs, h.rest_positions):
        assert torch.allclose(a, b, atol=1e-6)
    # attributes: plain mean of the children (level by level)
    attrs = torch.randn(3000, 5)
    means = h.aggregate_mean(attrs)
    c0 = int(h.parents[0][0])
    assert torch.allclose(means[1][c0], attrs[h.parents[0] == c0].mean(0), atol=1e-6)
    c1 = int(h.parents[1][0])
    assert torch.allclose(means[2][c1], means[1][h.parents[1] == c1].mean(0), atol=1e-6)
    # offsets to the anchor
    offs = h.offsets()
    assert len(offs) == h.root_level
    assert torch.allclose(offs[0], h.rest_positions[0] - h.rest_positions[1][h.parents[0]])
    # sums up the tree
    ones = h.aggregate_sum(torch.ones(3000, 1))
    assert float(ones[-1]) == 3000.0
    with pytest.raises(ValueError, match="level 0 has 3000 nodes"):
        h.aggregate_sum(torch.ones(10, 1))


def test_hierarchy_serialisation_roundtrip(rope_hierarchy, tmp_path):
    _, _, h = rope_hierarchy
    path = tmp_path / "h.pt"
    torch.save(h.to_dict(), path)
    h2 = Hierarchy.from_dict(torch.load(path, weights_only=True))
    assert h2.thresholds == h.thresholds and h2.sizes == h.sizes
    for a, b in zip(h.parents, h2.parents):
        assert torch.equal(a, b)
    for a, b in zip(h.rest_positions, h2.rest_positions):
        assert torch.equal(a, b)
    bad = h.to_dict()
    bad["format"] = "nope"
    with pytest.raises(ValueError, match="format"):
        Hierarchy.from_dict(bad)
    bad = h.to_dict()
    bad["parents"][0] = bad["parents"][0].clone()
    bad["parents"][0][0] = 10**6
    with pytest.raises(ValueError, match="out of range"):
        Hierarchy.from_dict(bad)


def test_build_hierarchy_13k_is_fast_and_validates():
    sp = synthetic_rope(13000, seed=0)
    t0 = time.perf_counter()
    h = build_hierarchy(sp.means, sp.mass, [0.02, 0.2])
    elapsed = time.perf_counter() - t0
    assert h.sizes[0] == 13000 and h.sizes[-1] == 1
    assert elapsed < 20.0, f"hierarchy build took {elapsed:.1f}s"  # ~0.3 s measured; generous for shared CI
    with pytest.raises(ValueError, match="increasing"):
        build_hierarchy(sp.means, sp.mass, [0.2, 0.02])
    with pytest.raises(ValueError, match="masses"):
        build_hierarchy(sp.means, -sp.mass, [0.02])
