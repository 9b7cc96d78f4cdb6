"""The PhysTwin-style spring-mass baseline (soma_ros.core.spring_mass): rest, grasp and lift,
release, stability at the parameter bounds, gradients, skinning, persistence."""

from __future__ import annotations

import math

import pytest
import torch

from soma_ros.core.scenes import synthetic_rope
from soma_ros.core.simulator import RobotAction, SceneContext
from soma_ros.core.spring_mass import SpringMass, SpringMassConfig, farthest_point_sampling

torch.set_num_threads(1)


def _rope_and_scene():
    sp = synthetic_rope(1500, center=(0.5, 0.0, 0.0), seed=1)
    return sp, SceneContext.table(0.0, dt=1.0 / 30.0)


def _jaws(center: torch.Tensor, opening: float, z: float) -> torch.Tensor:
    """30 control points: two 5 x 3 pads at +-opening/2 along y, spanning 1.8 cm in x and z."""
    u = torch.linspace(-0.009, 0.009, 5)
    v = torch.linspace(-0.009, 0.009, 3)
    uu, vv = torch.meshgrid(u, v, indexing="ij")
    a = torch.stack([vv.reshape(-1), torch.full((15,), opening / 2), uu.reshape(-1) + z], -1)
    b = a.clone()
    b[:, 1] = -opening / 2
    return torch.cat([a, b]) + torch.tensor([float(center[0]), float(center[1]), 0.0])


def _grasp_lift(ep, frames=30, lift_per_frame=0.003, release_at=None):
    mid = ep.rest[(ep.rest[:, 0] - 0.5).abs().argmin()]
    acts = []
    for t in range(frames):
        z = 0.06 - 0.052 * min(t, 8) / 8 if t <= 8 else 0.008 + (lift_per_frame * (t - 12) if t > 12 else 0.0)
        op = 0.08 if t < 9 else max(0.008, 0.08 - 0.024 * (t - 8))
        if release_at is not None and t >= release_at:
            op = 0.08
        acts.append(RobotAction(_jaws(mid, op, z), op / 0.08))
    return acts, mid


def test_fps_is_deterministic_and_spread():
    pts = torch.rand(500, 3, generator=torch.Generator().manual_seed(0))
    i1 = farthest_point_sampling(pts, 20)
    assert torch.equal(i1, farthest_point_sampling(pts, 20)) and len(set(i1.tolist())) == 20
    # the sample covers the cube: every point is within 0.45 of a sample
    d = torch.cdist(pts, pts[i1]).min(1).values
    assert float(d.max()) < 0.45


def test_rest_without_robot_stays_put_and_splats_follow():
    sp, scene = _rope_and_scene()
    sm = SpringMass(SpringMassConfig(num_nodes=60, substeps=20, total_mass=0.05))
    ep = sm.init_episode(sp, scene)
    assert ep.num_nodes == 60 and ep.springs.shape[0] == 2 and (ep.springs[0] < ep.springs[1]).all()
    with torch.no_grad():
        nodes = sm.rollout(ep, [None] * 6)
    assert nodes.shape == (6, 60, 3)
    assert float((nodes - nodes[0]).abs().max()) < 1e-6
    # skinning at rest reproduces the splats exactly (rotations = identity)
    means, covs = sm.carry(ep, nodes[-1])
    torch.testing.assert_close(means, sp.means, atol=1e-6, rtol=0)
    torch.testing.assert_close(covs, sp.covariances(), atol=1e-9, rtol=1e-4)
    # a rigid translation of the nodes translates the splats
    m2, _ = sm.carry(ep, nodes[-1] + torch.tensor([0.1, 0.0, 0.0]))
    torch.testing.assert_close(m2, sp.means + torch.tensor([0.1, 0.0, 0.0]), atol=1e-5, rtol=0)


def test_grasp_lifts_and_release_drops():
    sp, scene = _rope_and_scene()
    sm = SpringMass(SpringMassConfig(num_nodes=60, substeps=20, total_mass=0.05))
    ep = sm.init_episode(sp, scene)
    acts, mid = _grasp_lift(ep, frames=30, lift_per_frame=0.003)
    with torch.no_grad():
        nodes = sm.rollout(ep, acts)
    assert torch.isfinite(nodes).all()
    # the gripper rose 0.003 * 17 = 5.1 cm above the grasp; the grasped part follows it
    grasped = (ep.rest - mid).norm(dim=-1) < 0.015
    dz = nodes[-1, grasped, 2] - nodes[0, grasped, 2]
    assert float(dz.mean()) == pytest.approx(0.051, abs=0.012)
    # the rope's far ends stay lower than the grasped part (it hangs)
    ends = (ep.rest[:, 0] - 0.5).abs() > 0.15
    assert float(nodes[-1, ends, 2].mean()) < float(nodes[-1, grasped, 2].mean()) - 0.02
    # no node sinks through the table
    assert float(nodes[..., 2].min()) >= -1e-6
    # releasing at frame 20 lets the rope fall back
    acts_r, _ = _grasp_lift(ep, frames=30, lift_per_frame=0.003, release_at=20)
    with torch.no_grad():
        nodes_r = sm.rollout(ep, acts_r)
    assert float(nodes_r[-1, grasped, 2].mean()) < float(nodes[-1, grasped, 2].mean()) - 0.02


def test_stable_at_parameter_bounds_and_differentiable():
    sp, scene = _rope_and_scene()
    sm = SpringMass(SpringMassConfig(num_nodes=40, substeps=10, total_mass=0.05))
    ep = sm.init_episode(sp, scene)
    acts, _ = _grasp_lift(ep, frames=20, lift_per_frame=0.004)
    with torch.no_grad():
        for p in (sm.theta_stiffness, sm.theta_dashpot, sm.theta_grip):
            p.fill_(12.0)  # sigmoid ~ 1: at the stability bound
        nodes = sm.rollout(ep, acts)
    assert torch.isfinite(nodes).all() and float(nodes.abs().max()) < 2.0
    sm2 = SpringMass(SpringMassConfig(num_nodes=40, substeps=10, total_mass=0.05))
    nodes = sm2.rollout(ep, acts)
    loss = nodes[1:, :, 2].mean()
    loss.backward()
    grads = {n: p.grad for n, p in sm2.named_parameters()}
    assert all(g is not None and torch.isfinite(g) for g in grads.values())
    assert abs(float(grads["theta_stiffness"])) > 0 and abs(float(grads["theta_grip"])) > 0
    with torch.no_grad():
        phys = sm2.physical(ep)
    assert 0 < float(phys["stiffness"]) < ep.k_max and 0 < float(phys["friction"]) < 5


def test_payload_roundtrip():
    sm = SpringMass(SpringMassConfig(num_nodes=33, total_mass=0.2))
    with torch.no_grad():
        sm.log_drag.fill_(math.log(3.0))
    sm2 = SpringMass.from_payload(sm.to_payload({"note": "x"}))
    assert sm2.config.num_nodes == 33 and sm2.describe()["drag_per_s"] == pytest.approx(3.0)
    with pytest.raises(ValueError, match="spring-mass"):
        SpringMass.from_payload({"format": "other"})
    with pytest.raises(ValueError, match="num_nodes"):
        SpringMassConfig(num_nodes=1).validate()


def test_saved_model_is_verified_on_load(tmp_path):
    """spring_mass.pt carries a content checksum: a flipped weight is refused with one line naming the file."""
    from soma_ros.evaluation.baselines import load_model, save_spring_mass

    path = save_spring_mass(tmp_path / "spring_mass.pt", SpringMass(SpringMassConfig(num_nodes=20, total_mass=0.1)))
    assert load_model(path).__class__.__name__ == "SpringMassModel"
    payload = torch.load(path, weights_only=True)
    assert payload["checksum"].startswith("sha256:")
    name = next(k for k, v in payload["state_dict"].items() if v.numel())
    payload["state_dict"][name] = payload["state_dict"][name] + 1.0
    torch.save(payload, path)
    with pytest.raises(ValueError, match=r"spring_mass\.pt: spring-mass model is corrupt") as err:
        load_model(path)
    assert "\n" not in str(err.value)


class _SyntheticEpisode:
    """The parts of soma_ros.data.dataset.EpisodeData that fit_spring_mass reads, with 'observed' points
    made by a spring-mass model of known parameters (full point sets, not partial views)."""

    def __init__(self, name, actions, points):
        self.name, self._actions, self._points = name, actions, points
        self.dt = 1.0 / 30.0
        self.num_frames = len(actions)

    def actions(self, frames):
        return [self._actions[t] for t in frames]

    def object_points(self, frames):
        return torch.cat([self._points[t] for t in frames]), None


def test_fit_recovers_a_known_stiffness():
    from soma_ros.evaluation.baselines import SpringMassFitConfig, fit_spring_mass

    sp, scene = _rope_and_scene()
    mcfg = SpringMassConfig(num_nodes=30, substeps=8, total_mass=0.05)
    truth = SpringMass(mcfg)
    with torch.no_grad():
        truth.theta_stiffness.fill_(math.log(0.03 / 0.97))  # a very soft rope: it stretches when lifted
    ep_t = truth.init_episode(sp, scene)
    acts, _ = _grasp_lift(ep_t, frames=20, lift_per_frame=0.006)
    with torch.no_grad():
        nodes = truth.rollout(ep_t, acts)
        pts = [truth.carry(ep_t, nodes[t], rotations=False)[0][::7] for t in range(len(acts))]
    ep = _SyntheticEpisode("synthetic", acts, pts)
    fc = SpringMassFitConfig(iters=10, lr=0.4, max_points=300, frame_stride=2, model=mcfg)
    model, info = fit_spring_mass([(ep, sp)], scene, fc, progress=False, log=lambda s: None)
    losses = [h["loss"] for h in info["history"]]
    assert info["loss_final_all_train"] < 0.3 * losses[0]
    # the fitted stiffness moved from the initial 0.5 of the stability bound to near the true 0.03
    assert info["parameters"]["stiffness_fraction"] < 0.1
    assert info["train_episodes"] == ["synthetic"]
