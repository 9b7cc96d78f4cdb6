"""The simulator step: rest, stability over long rollouts, propagation, gradients."""

from __future__ import annotations

import copy
import dataclasses
import math

import pytest
import torch

from soma_ros.core.cameras import Cameras, look_at
from soma_ros.core.config import ModelConfig, load_model_config
from soma_ros.core.geometry import quat_multiply, quat_normalize, quat_to_rotmat
from soma_ros.core.render import render
from soma_ros.core.scenes import synthetic_rope
from soma_ros.core.simulator import RobotAction, SceneContext, Simulator

torch.set_num_threads(1)


def _rope(n=1500, seed=0):
    # lies on z = 0 (bottom of the tube touches the table), centred at the origin
    return synthetic_rope(n, seed=seed, center=(0.0, 0.0, 0.0))


def _sweep(i: int, cp0: torch.Tensor, period: int = 120) -> RobotAction:
    """Control points sweeping back and forth across the rope, gripper opening and closing."""
    ph = 2 * math.pi * i / period
    off = torch.tensor([0.05 * math.sin(ph), 0.04 * math.sin(2 * ph), 0.01 * (1 - math.cos(ph))])
    return RobotAction(cp0 + off, 0.5 + 0.5 * math.sin(3 * ph))


def _gripper_points(centre, n=30, radius=0.01, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.as_tensor(centre, dtype=torch.float32) + radius * torch.randn(n, 3, generator=g)


@pytest.mark.parametrize("model", ["cpu", "paper"])
def test_object_at_rest_on_table_stays_put_exactly(model):
    """Robot far, table below, random weights: the initial state is a bitwise fixed point.

    Why exact: the step subtracts the network's outputs at the initial state (computed in
    init_state by the same code on the same inputs), so at the initial state the update is
    exactly 0 and every position/deformation is recomputed from identical inputs; CPU
    kernels are deterministic for identical inputs in one process. Tolerance 0.
    """
    torch.manual_seed(1)
    sp = _rope(1500)
    sim = Simulator(load_model_config(model)).eval()
    scene = SceneContext.table()
    far = RobotAction(_gripper_points([2.0, 2.0, 0.5]), 1.0)
    with torch.no_grad():
        s0 = sim.init_state(sp, scene)
        f = sim.forces(s0, far)
        assert f.abs().max() > 0  # gravity and support are acting, they balance by construction
        states = sim.rollout(s0, [far] * (100 if model == "cpu" else 20))
    last = states[-1]
    assert torch.equal(last.means, s0.means)
    assert torch.equal(last.covs, s0.covs)
    assert torch.equal(last.quats, s0.quats)
    assert float((s0.means - sp.means).abs().max()) < 1e-6  # init reproduces the splats (float rounding)
    assert torch.allclose(s0.covs, sp.covariances(), atol=1e-12)
    # ...and the same model does respond when the robot comes into reach (the test above is not vacuous)
    cp0 = _gripper_points(sp.means[sp.means[:, 0] > 0.15].mean(0).tolist())
    with torch.no_grad():
        pushed = sim.rollout(s0, [RobotAction(cp0 + torch.tensor([0.0, 0.003 * i, 0.0]), 0.0) for i in range(10)])
    assert float((pushed[-1].means - s0.means).norm(dim=-1).max()) > 1e-5


def test_force_free_reference_lets_gravity_act():
    torch.manual_seed(2)
    sp = _rope(800)
    sim = Simulator(load_model_config("cpu")).eval()
    with torch.no_grad():
        s0 = sim.init_state(sp, SceneContext.table(), reference="force_free")
        s = sim.rollout(s0, [None] * 5)[-1]
    assert float((s.means - s0.means).norm(dim=-1).max()) > 1e-6
    with pytest.raises(ValueError, match="reference"):
        sim.init_state(sp, SceneContext.table(), reference="magic")


def test_long_rollout_13k_random_weights_is_finite_and_bounded():
    """1,000 steps at 13,000 splats, robot sweeping through the rope, wind and drag on.

    Bounds that hold by construction (module docstring of soma_ros.core.simulator):
    * the root moves at most max_speed * dt per step: |x_root(T) - x_root(0)| <= T dt max_speed;
    * every splat stays within ``extent_bound`` of the root (anchor offsets times the bounded
      stretch plus the residual limits);
    * det F = 1 at every level, so every covariance keeps its determinant (volume).
    """
    torch.manual_seed(3)
    sp = synthetic_rope(13000, seed=4, center=(0.0, 0.0, 0.0))
    cfg = load_model_config("cpu")
    sim = Simulator(cfg).eval()
    sim.add_effect({"name": "wind", "accel": [0.5, 0.0, 0.0]})
    sim.add_effect({"name": "linear_drag", "coeff": 0.2})
    scene = SceneContext.table()
    cp0 = _gripper_points([0.1, 0.0, 0.01])
    T = 1000
    with torch.no_grad():
        s0 = sim.init_state(sp, scene)
        root0 = s0.positions[-1].clone()
        bound = sim.extent_bound(s0)
        det0 = torch.linalg.det(s0.covs.double())
        s = s0
        max_disp = 0.0
        for t in range(1, T + 1):
            s = sim.step(s, _sweep(t, cp0))
            if t % 100 == 0 or t == T:
                assert torch.isfinite(s.means).all() and torch.isfinite(s.covs).all(), t
                root = s.positions[-1]
                assert float((root - root0).norm()) <= t * scene.dt * cfg.dynamics.max_speed + 1e-6
                ext = (s.means - root).norm(dim=-1)
                assert bool((ext <= bound + 1e-5).all()), float((ext - bound).max())
                det = torch.linalg.det(s.covs.double())
                assert torch.allclose(det, det0, rtol=1e-3), float(((det - det0) / det0).abs().max())
                max_disp = max(max_disp, float((s.means - s0.means).norm(dim=-1).max()))
    assert max_disp > 1e-4  # it did move


def test_propagation_and_deformation_invariants():
    torch.manual_seed(4)
    sp = _rope(1200)
    sim = Simulator(load_model_config("cpu")).eval()
    cp0 = _gripper_points([0.15, 0.0, 0.01])
    with torch.no_grad():
        s0 = sim.init_state(sp, SceneContext.table())
        s = sim.rollout(s0, [_sweep(i, cp0, 30) for i in range(1, 16)])[-1]
    h, ep = sim.hierarchy, s.episode
    L = h.root_level
    for l in range(1, L + 1):
        assert torch.allclose(torch.linalg.det(s.deform[l].double()), torch.ones(h.sizes[l], dtype=torch.float64), atol=1e-4)
        assert torch.allclose(s.rot[l].norm(dim=-1), torch.ones(h.sizes[l]), atol=1e-5)
        if l < L:  # x = anchor' + Fbar_anchor (X - X_anchor) + residual
            p = h.parents[l]
            c = s.positions[l + 1][p] + (s.deform[l + 1][p] @ ep.offsets[l][..., None])[..., 0]
            assert torch.allclose(s.carry[l], c, atol=1e-6)
            assert torch.allclose(s.positions[l], c + s.resid[l], atol=1e-6)
            assert bool((s.resid[l].norm(dim=-1) <= ep.residual_limit[l] + 1e-6).all())
    # splats: carried by their fine cluster; Sigma' = F Sigma F^T
    p0 = h.parents[0]
    F = s.deform[1][p0]
    assert torch.allclose(s.means, s.positions[1][p0] + (F @ ep.offsets[0][..., None])[..., 0], atol=1e-6)
    assert torch.allclose(s.covs, F @ ep.rest_covs @ F.transpose(1, 2), atol=1e-9)
    assert float((s.means - s0.means).norm(dim=-1).max()) > 1e-5
    # mass consistency between levels: ~0 at rest, > 0 once levels move independently
    assert float(sim.momentum_loss(s0)) < 1e-16
    assert float(sim.momentum_loss(s)) > 1e-12
    # the splat quaternion is the product of the accumulated rotations (root first) times the rest one
    rbar = s.rot[L]
    for l in range(L - 1, 0, -1):
        rbar = quat_multiply(s.rot[l], rbar[h.parents[l]])
    q = quat_normalize(quat_multiply(rbar[p0], ep.rest_quats))
    assert torch.allclose(s.quats, q, atol=1e-6)
    assert float((quat_to_rotmat(s.quats) - quat_to_rotmat(ep.rest_quats)).abs().max()) > 1e-6  # it rotated
    # exported splats reproduce the covariances
    out = s.to_splats(sp)
    assert torch.allclose(out.covariances(), s.covs, atol=1e-8)
    assert torch.equal(out.means, s.means)


def _grad_scene(model: str):
    torch.manual_seed(5)
    sp = _rope(1200, seed=6)
    sim = Simulator(load_model_config(model))
    for e in ("wind", "linear_drag", "quadratic_drag"):
        sim.add_effect(e)
    # table 2 mm above the rope's lowest splats: support and its penetration penalty are active
    scene = SceneContext.table(height=0.002)
    cp0 = sp.means[sp.means[:, 0] > 0.17][:30].clone()
    W, H = 48, 36
    K = torch.tensor([[0.8 * W, 0.0, W / 2], [0.0, 0.8 * W, H / 2], [0.0, 0.0, 1.0]])
    cams = Cameras.from_cam_to_world(K, look_at([0.0, -0.35, 0.35], [0.0, 0.0, 0.0]), W, H)
    return sp, sim, scene, cp0, cams


@pytest.mark.parametrize("model", ["cpu", "paper"])
def test_image_loss_gradient_reaches_every_parameter(model):
    """10-step rollout rendered by soma_ros.core.render; every trainable parameter gets a
    finite, non-zero gradient. Every effect is active: robot in reach and moving, splats
    within tau of (and some below) the table, wind/drag (zero-initialised) on a moving object."""
    sp, sim, scene, cp0, cams = _grad_scene(model)
    s0 = sim.init_state(sp, scene)
    actions = [RobotAction(cp0 + torch.tensor([0.0, 0.004 * i, 0.003 * i]), 0.3) for i in range(1, 11)]
    states = sim.rollout(s0, actions)
    target = torch.rand(cams.height, cams.width, 3, generator=torch.Generator().manual_seed(0))
    loss = sum(((render(s.means, s.covs, sp.colors(), sp.opacities, cams).rgb[0] - target) ** 2).mean() for s in states)
    loss.backward()
    params = dict(sim.named_parameters())
    assert "splat_attrs" in params and "effects.terms.wind.accel" in params
    missing = [n for n, p in params.items() if p.grad is None]
    bad = [n for n, p in params.items() if p.grad is not None and not torch.isfinite(p.grad).all()]
    zero = [n for n, p in params.items() if p.grad is not None and p.grad.abs().max() == 0]
    assert not missing and not bad and not zero, (missing, bad, zero)


def test_inputs_are_validated():
    with pytest.raises(ValueError, match="object's side"):
        SceneContext(torch.tensor([0.0, 0.0, -9.81]), torch.tensor([0.0, 0.0, -1.0]), 0.0, 0.03)
    with pytest.raises(ValueError, match="dt"):
        SceneContext.table(dt=0.0)
    with pytest.raises(ValueError, match=r"\[P, 3\]"):
        RobotAction(torch.zeros(30, 2), 0.5)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        RobotAction(torch.zeros(30, 3), 1.5)
    a = RobotAction(torch.zeros(30, 3), torch.tensor([0.25]))
    assert a.gripper.shape == () and float(a.gripper) == 0.25
    sim = Simulator(load_model_config("cpu"))
    s0 = sim.init_state(_rope(500), SceneContext.table())
    with pytest.raises(ValueError, match="bound to 500 splats"):
        sim.init_state(_rope(400), SceneContext.table())
    with pytest.raises(TypeError, match="RobotAction"):
        sim.step(s0, torch.zeros(30, 3))


def test_normalizers_fit_in_training_and_freeze():
    sim = Simulator(load_model_config("cpu"))  # normalizer.mode: fit
    sp = _rope(600)
    cp0 = _gripper_points([0.15, 0.0, 0.01])
    sim.train()
    s = sim.init_state(sp, SceneContext.table())
    with torch.no_grad():
        sim.rollout(s, [_sweep(i, cp0, 20) for i in range(3)])
    n1 = [float(m.count) for m in sim.node_norms]
    assert n1[1] > 0 and n1[0] == 0  # cluster levels seen; no network on the splat level (cpu model)
    mean, std = sim.node_norms[1].stats()
    assert torch.isfinite(mean).all() and (std > 0).all()
    sim.eval()
    with torch.no_grad():
        sim.rollout(sim.init_state(sp, SceneContext.table()), [_sweep(0, cp0)])
    assert [float(m.count) for m in sim.node_norms] == n1  # frozen in eval mode


def test_float64_truncated_backprop_and_foreign_states():
    torch.manual_seed(6)
    sp = _rope(700)
    sim = Simulator(load_model_config("cpu")).double()
    sim.set_normalizer_fitting(False)  # fixed statistics: the reference is reproducible below
    cp0 = _gripper_points([0.15, 0.0, 0.01]).double()
    s0 = sim.init_state(sp, SceneContext.table())
    assert s0.means.dtype == torch.float64 and sim.hierarchy.rest_positions[1].dtype == torch.float64
    s = sim.rollout(s0, [RobotAction(cp0 + 0.002 * i, 0.5) for i in range(3)])[-1]
    cut = s.detach()
    assert not cut.means.requires_grad and torch.equal(cut.means, s.means)
    s2 = sim.step(cut, RobotAction(cp0 + 0.01, 0.5))
    s2.means.sum().backward()  # the graph starts at the cut
    assert sim.gnn.decoder.last.weight.grad is not None and sim.splat_attrs.grad is None
    # refresh_reference: differentiable reference under the current weights, same outputs
    fresh = sim.refresh_reference(cut)
    for a, b in zip(fresh.episode.reference, s0.episode.reference):
        assert (a is None and b is None) or torch.allclose(a, b)
    sim.zero_grad()
    sim.step(fresh, RobotAction(cp0 + 0.01, 0.5)).means.sum().backward()
    assert sim.splat_attrs.grad is not None
    other = Simulator(load_model_config("cpu"))
    other.init_state(_rope(300), SceneContext.table())
    with pytest.raises(ValueError, match="another model"):
        other.step(cut, None)


def test_turned_network_frame_is_equivariant_and_keeps_rest():
    """``init_state(network_yaw=theta)``: the network sees the world turned by Q about gravity.

    Turning the whole episode (splats, robot) by Q and running the world-frame network must give
    exactly Q times the positions of the original episode run with the network in the turned
    frame: the same network inputs, so the same outputs, mapped back by Q^T. The hierarchy and the
    static graph are shared (a deep copy of the bound model), so only the frame differs. Random
    weights (non-zero output), a closed gripper sweeping through the rope, 12 steps, float64."""
    torch.manual_seed(5)
    sp = _rope(900).to(dtype=torch.float64)
    # the robot coupling (a physical term: equivariant); the cpu model's free-form robot force is an MLP
    # on world-frame vectors, which no turn of the network's frame makes equivariant
    base = load_model_config("cpu").to_dict()
    base["gnn"]["out_init_scale"] = 1.0
    base["effects"] = [{"name": "gravity"}, {"name": "support", "tau": 0.01, "gain": 1.0, "stiffness": 500.0},
                       {"name": "robot", "radius": 0.05, "form": "coupling", "carry": 0.5, "direct": True, "feature": False}]
    sim = Simulator(ModelConfig.from_dict(base)).double().eval()
    scene = SceneContext.table().to(dtype=torch.float64)
    theta = 0.7
    c, s_ = math.cos(theta), math.sin(theta)
    Q = torch.tensor([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    q = torch.tensor([math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2)], dtype=torch.float64)
    cp0 = _gripper_points([0.15, 0.0, 0.01]).double()
    acts = [_sweep(i, cp0, 30) for i in range(1, 13)]
    with torch.no_grad():
        s_a = sim.init_state(sp, scene, network_yaw=theta)  # binds the model to sp
        twin = copy.deepcopy(sim)
        turned = dataclasses.replace(sp, means=sp.means @ Q.T, quats=quat_multiply(q.expand_as(sp.quats), sp.quats))
        s_b = twin.init_state(turned, scene)
        a_states = sim.rollout(s_a, acts)
        b_states = twin.rollout(s_b, [RobotAction(a.control_points @ Q.T, a.gripper) for a in acts])
        plain = sim.rollout(sim.init_state(sp, scene), acts)
        physics_only = copy.deepcopy(sim).set_network(False).rollout(sim.init_state(sp, scene), acts)
    moved = float((a_states[-1].means - s_a.means).norm(dim=-1).max())
    assert moved > 1e-4
    assert float((a_states[-1].means - physics_only[-1].means).abs().max()) > 1e-5  # the network acts
    assert torch.allclose(b_states[-1].means, a_states[-1].means @ Q.T, atol=1e-9)
    assert torch.allclose(b_states[-1].covs, Q @ a_states[-1].covs @ Q.T, atol=1e-12)
    # the turn changes what a (non-equivariant) random network does; yaw 0 is the world frame
    assert float((plain[-1].means - a_states[-1].means).abs().max()) > 1e-6
    assert sim.init_state(sp, scene, network_yaw=0.0).episode.network_frame is None
    # at rest the turned frame still stays put exactly
    far = RobotAction(_gripper_points([2.0, 2.0, 0.5]).double(), 1.0)
    with torch.no_grad():
        r0 = sim.init_state(sp, scene, network_yaw=theta)
        r = sim.rollout(r0, [far] * 5)[-1]
    assert torch.equal(r.means, r0.means)
    with pytest.raises(ValueError, match="finite"):
        sim.init_state(sp, scene, network_yaw=float("nan"))
