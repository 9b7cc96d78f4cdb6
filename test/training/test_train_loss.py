"""Training loss terms on a hand-made frame: the depth term's two regions."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from soma_ros.core.calibration import Sim3
from soma_ros.training.config import ConfigError, load_train_config
from soma_ros.data.dataset import EpisodeData
from soma_ros.training.train import frame_terms

torch.set_num_threads(1)

H, W = 24, 32


def _episode(object_mask: torch.Tensor) -> EpisodeData:
    """One camera 0.5 m above the table plane z = 0, looking straight down; the measured depth
    is the table (0.5 m) everywhere but on ``object_mask`` (0.45 m: an object 5 cm high)."""
    T, C = 1, 1
    K = torch.tensor([[[30.0, 0.0, W / 2], [0.0, 30.0, H / 2], [0.0, 0.0, 1.0]]])
    c2w = torch.eye(4)
    c2w[:3, :3] = torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # optical z -> world -z
    c2w[2, 3] = 0.5
    depth = torch.full((T, C, H, W), 0.5)
    depth[0, 0][object_mask] = 0.45
    om = object_mask.reshape(1, 1, H, W).clone()
    rm = torch.zeros(T, C, H, W, dtype=torch.bool)
    return EpisodeData(
        name="hand", path=None, stamps_ns=torch.zeros(T, dtype=torch.long), dt=1 / 30, camera_names=["cam"],
        width=W, height=H, K=K, cam_to_world=c2w.reshape(1, 1, 4, 4), rgb=torch.zeros(T, C, H, W, 3),
        depth=depth, object_mask=om, robot_mask=rm, loss_mask=om & ~rm, joint_names=["j"],
        joint_positions=torch.zeros(T, 1), control_points=torch.zeros(T, 1, 3), gripper=torch.ones(T),
        gripper_opening=torch.ones(T), ee_pose=torch.eye(4).reshape(1, 4, 4), base_to_sim=Sim3.identity(),
    )


def _splat_state(xy, z: float) -> SimpleNamespace:
    means = torch.tensor([[xy[0], xy[1], z]])
    covs = (torch.eye(3) * 0.01 ** 2)[None]
    return SimpleNamespace(means=means, covs=covs)


def _cfg(region: str):
    return load_train_config("tiny", overrides={"loss": {"depth_weight": 1.0, "depth_region": region,
                                                         "points_weight": 0.0}})


def test_scored_depth_term_sees_splats_over_the_table_and_object_region_does_not():
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[2:6, 2:6] = True  # the measured object, in a corner
    ep = _episode(mask)
    plane = (torch.tensor([0.0, 0.0, 1.0]), 0.0)
    colors, opac = torch.ones(1, 3), torch.ones(1)
    stray = _splat_state((0.0, 0.0), 0.1)  # a splat 10 cm above the table, in the image centre, off the object
    obj = frame_terms(stray, colors, opac, ep, 0, _cfg("object"), "cpu", points=torch.zeros(0, 3))
    scored = frame_terms(stray, colors, opac, ep, 0, _cfg("scored"), "cpu", points=torch.zeros(0, 3), plane=plane)
    # object region: the splat is not on object pixels; those render nothing (depth 0): error 0.45 m each
    assert float(obj["depth"]) == pytest.approx(0.45, abs=1e-4)
    # scored region: object pixels (nothing rendered there -> the table, 0.5 vs 0.45: 0.05 m) and the
    # pixels where the stray splat renders (about 0.4 m vs the table 0.5 m: ~0.1 m each)
    assert 0.05 < float(scored["depth"]) < 0.1
    # moving the splat onto the table (z = 0) at the same pixels lowers the scored term; the object one stays
    on_table = _splat_state((0.0, 0.0), 0.0)
    s2 = frame_terms(on_table, colors, opac, ep, 0, _cfg("scored"), "cpu", points=torch.zeros(0, 3), plane=plane)
    assert float(s2["depth"]) < float(scored["depth"]) - 0.01
    # differentiable: the gradient pushes the stray splat down towards the table (world -z)
    st = _splat_state((0.0, 0.0), 0.1)
    st.means.requires_grad_(True)
    frame_terms(st, colors, opac, ep, 0, _cfg("scored"), "cpu", points=torch.zeros(0, 3), plane=plane)["depth"].backward()
    assert float(st.means.grad[0, 2]) > 0  # the loss grows with height


def test_scored_depth_needs_the_plane_and_bad_regions_fail_clearly():
    ep = _episode(torch.zeros(H, W, dtype=torch.bool))
    with pytest.raises(ValueError, match="plane"):
        frame_terms(_splat_state((0.0, 0.0), 0.1), torch.ones(1, 3), torch.ones(1), ep, 0, _cfg("scored"), "cpu",
                    points=torch.zeros(0, 3))
    with pytest.raises(ConfigError, match="depth_region"):
        load_train_config("tiny", overrides={"loss": {"depth_region": "everywhere"}})
