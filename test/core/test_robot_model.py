"""RobotModel: FK against yourdfpy, mimic joints, joint-state mapping, gripper, control points."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import yourdfpy

from soma_ros.core.robot import RobotModel, control_point_pattern
from soma_ros.core.robot_config import RobotConfig, RobotConfigError, load_robot_config

torch.set_num_threads(1)

N_CONFIGS = 1000


@pytest.fixture(scope="module")
def panda() -> RobotModel:
    return RobotModel.from_config("panda", dtype=torch.float64)


@pytest.fixture(scope="module")
def arx5() -> RobotModel:
    return RobotModel.from_config("arx5", dtype=torch.float64)


def _yourdfpy_fk(model: RobotModel, q: torch.Tensor) -> dict[str, np.ndarray]:
    robot = yourdfpy.URDF.load(
        str(model.config.urdf), load_meshes=False, build_collision_scene_graph=False, load_collision_meshes=False
    )
    # our q holds exactly yourdfpy's actuated (non-mimic) joints
    assert sorted(robot.actuated_joint_names) == sorted(model.joint_names)
    out = {link: np.zeros((q.shape[0], 4, 4)) for link in model.link_names}
    for i in range(q.shape[0]):
        robot.update_cfg(dict(zip(model.joint_names, q[i].tolist())))
        for link in model.link_names:
            out[link][i] = robot.get_transform(link, model.base_link)
    return out


@pytest.mark.parametrize("name", ["panda", "arx5"])
def test_fk_matches_yourdfpy(name: str) -> None:
    model = RobotModel.from_config(name, dtype=torch.float64)
    q = model.sample_q(N_CONFIGS, torch.Generator().manual_seed(7))
    lo, hi = model.joint_limits()
    assert bool(((q >= lo) & (q <= hi)).all())
    ours = model.fk(q)
    ref = _yourdfpy_fk(model, q)
    assert set(ours) == set(model.link_names)
    for link in model.link_names:
        T = ours[link].numpy()
        assert T.shape == (N_CONFIGS, 4, 4)
        pos_err = np.abs(T[:, :3, 3] - ref[link][:, :3, 3]).max()
        rot_err = np.abs(T[:, :3, :3] - ref[link][:, :3, :3]).max()
        assert pos_err < 1e-6, f"{name} {link}: position error {pos_err:.3g} m"
        assert rot_err < 1e-6, f"{name} {link}: rotation error {rot_err:.3g}"
    ee = model.ee_pose(q).numpy()
    assert np.abs(ee - ref[model.ee_link]).max() < 1e-6


@pytest.mark.parametrize("name", ["panda", "arx5"])
def test_fk_float64_is_exact(name: str) -> None:
    """Joint origins are rebuilt in float64 (pytorch_kinematics alone builds them in float32)."""
    model = RobotModel.from_config(name, dtype=torch.float64)
    assert model.exact_offsets
    T = model.fk(model.sample_q(200, torch.Generator().manual_seed(8)))
    for link, Tl in T.items():
        R = Tl[:, :3, :3]
        err = (R.transpose(1, 2) @ R - torch.eye(3, dtype=torch.float64)).abs().max()
        assert err < 1e-12, f"{name} {link}: rotation not orthonormal ({float(err):.3g})"
        assert torch.equal(Tl[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(200, 4))


def test_float32_model_is_close(panda: RobotModel) -> None:
    q = panda.sample_q(64, torch.Generator().manual_seed(3))
    m32 = panda.to(dtype=torch.float32)
    assert panda.dtype == torch.float64  # to() returns a new model, leaves this one alone
    T32 = m32.ee_pose(q.float())
    assert T32.dtype == torch.float32
    assert (T32.double() - panda.ee_pose(q)).abs().max() < 2e-6


def test_mimic_finger_follows_leader(panda: RobotModel) -> None:
    """finger_joint2 mimics finger_joint1: the two fingers open symmetrically about the hand."""
    q = panda.sample_q(20, torch.Generator().manual_seed(0))
    q[:, -1] = torch.linspace(0.0, 0.04, 20, dtype=torch.float64)
    T = panda.fk(q, links=["panda_hand", "panda_leftfinger", "panda_rightfinger"])
    hand_inv = torch.linalg.inv(T["panda_hand"])
    left = (hand_inv @ T["panda_leftfinger"])[:, :3, 3]
    right = (hand_inv @ T["panda_rightfinger"])[:, :3, 3]
    j1 = q[:, -1]
    torch.testing.assert_close(left[:, 1], j1, atol=1e-7, rtol=0)
    torch.testing.assert_close(right[:, 1], -j1, atol=1e-7, rtol=0)  # axis 0 -1 0, multiplier 1
    torch.testing.assert_close(left[:, 2], torch.full_like(j1, 0.0584), atol=1e-7, rtol=0)
    # the full joint vector really contains the mimic joint
    full = panda.full_joint_vector(q)
    i2 = panda.pk_joint_names.index("panda_finger_joint2")
    torch.testing.assert_close(full[:, i2], j1)


def test_fk_is_differentiable(panda: RobotModel) -> None:
    q = panda.sample_q(4, torch.Generator().manual_seed(5)).requires_grad_(True)
    p = panda.ee_pose(q)[:, :3, 3].sum()
    (g,) = torch.autograd.grad(p, q)
    eps = 1e-6
    num = torch.zeros_like(q)
    with torch.no_grad():
        for k in range(panda.n_joints):
            dq = torch.zeros_like(q)
            dq[:, k] = eps
            num[:, k] = (panda.ee_pose(q + dq)[:, :3, 3].sum(-1) - panda.ee_pose(q - dq)[:, :3, 3].sum(-1)) / (2 * eps)
    torch.testing.assert_close(g, num, atol=1e-5, rtol=1e-5)


def test_base_link_other_than_root() -> None:
    cfg = load_robot_config("panda")
    import dataclasses

    sub = RobotModel(
        dataclasses.replace(cfg, base_link="panda_link2", arm_joints=None), dtype=torch.float64
    )
    full = RobotModel(dataclasses.replace(cfg, arm_joints=None), dtype=torch.float64)
    assert sub.arm_joint_names == ["panda_joint3", "panda_joint4", "panda_joint5", "panda_joint6", "panda_joint7"]
    q_full = full.sample_q(10, torch.Generator().manual_seed(2))
    T = full.fk(q_full, links=["panda_link2", "panda_hand"])
    expected = torch.linalg.inv(T["panda_link2"]) @ T["panda_hand"]
    q_sub = q_full[:, 2:]  # joints 3..7 + finger
    torch.testing.assert_close(sub.ee_pose(q_sub), expected, atol=1e-9, rtol=0)


# ---------------------------------------------------------------- joint states
def test_q_from_joint_state_reorders_and_ignores_extras(panda: RobotModel) -> None:
    names = list(reversed(panda.joint_names)) + ["panda_finger_joint2", "some_other_joint"]
    vals = list(reversed([0.1 * (i + 1) for i in range(panda.n_joints)])) + [0.5, 9.0]
    q = panda.q_from_joint_state(names, vals)
    torch.testing.assert_close(q, torch.tensor([0.1 * (i + 1) for i in range(panda.n_joints)], dtype=torch.float64))
    # batched positions [T, J]
    qb = panda.q_from_joint_state(names, np.stack([vals, vals]))
    assert qb.shape == (2, panda.n_joints)


def test_q_from_joint_state_errors(panda: RobotModel) -> None:
    names = [n for n in panda.joint_names if n not in ("panda_joint3", "panda_finger_joint1")]
    with pytest.raises(ValueError, match="panda_joint3, panda_finger_joint1"):
        panda.q_from_joint_state(names, [0.0] * len(names))
    with pytest.raises(ValueError, match="twice"):
        panda.q_from_joint_state(panda.joint_names + ["panda_joint1"], [0.0] * (panda.n_joints + 1))
    vals = [0.0] * panda.n_joints
    vals[4] = float("nan")
    with pytest.raises(ValueError, match="panda_joint5"):
        panda.q_from_joint_state(panda.joint_names, vals)
    with pytest.raises(ValueError, match="positions of shape"):
        panda.q_from_joint_state(panda.joint_names, [0.0] * 3)
    with pytest.raises(ValueError, match=r"\[B, 8\]"):
        panda.ee_pose(torch.zeros(8, dtype=torch.float64))


def test_joint_aliases() -> None:
    import dataclasses

    cfg = dataclasses.replace(load_robot_config("arx5"), joint_aliases={"arm_j1": "joint1", "grip": "gripper"})
    m = RobotModel(cfg, dtype=torch.float64)
    names = ["joint6", "joint5", "joint4", "joint3", "joint2", "arm_j1", "grip"]
    q = m.q_from_joint_state(names, [6.0, 5.0, 4.0, 3.0, 2.0, 1.0, 0.03])
    torch.testing.assert_close(q, torch.tensor([1.0, 2, 3, 4, 5, 6], dtype=torch.float64))
    opening, c = m.gripper_state(names, [6.0, 5.0, 4.0, 3.0, 2.0, 1.0, 0.03])
    assert float(opening) == pytest.approx(0.03)


# ---------------------------------------------------------------- gripper
def test_gripper_state_panda(panda: RobotModel) -> None:
    names = panda.joint_names + ["panda_finger_joint2"]
    vals = [0.0] * 7 + [0.02, 0.02]
    opening, c = panda.gripper_state(names, vals)
    assert float(opening) == pytest.approx(0.04)
    assert float(c) == pytest.approx(0.5)
    # opening from q matches, and c clips outside the range
    q = panda.q_from_joint_state(names, vals)[None]
    assert float(panda.opening_from_q(q)[0]) == pytest.approx(0.04)
    assert float(panda.normalize_opening(torch.tensor(0.1))) == 1.0
    assert float(panda.normalize_opening(torch.tensor(-0.001))) == 0.0
    assert panda.opening_range == (0.0, 0.08)


def test_gripper_state_arx5_external_joint(arx5: RobotModel) -> None:
    assert "gripper" not in arx5.joint_names and arx5.gripper_joint_names == ["gripper"]
    names = ["gripper", "joint1", "joint2", "joint3", "joint4", "joint5", "joint6"]
    opening, c = arx5.gripper_state(names, [[0.0425] + [0.0] * 6, [0.085] + [0.0] * 6])
    torch.testing.assert_close(opening, torch.tensor([0.0425, 0.085], dtype=torch.float64))
    torch.testing.assert_close(c, torch.tensor([0.5, 1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="gripper"):
        arx5.gripper_state(names[1:], [0.0] * 6)
    with pytest.raises(ValueError, match="pass the opening"):
        arx5.control_points(torch.zeros(1, 6, dtype=torch.float64))


def test_default_opening_model_from_urdf_mimic() -> None:
    """Without coeffs/range the Panda opening is finger1 + its mimic finger2, range from the limits."""
    import dataclasses

    from soma_ros.core.robot_config import GripperConfig

    cfg = dataclasses.replace(load_robot_config("panda"), gripper=GripperConfig(joints=("panda_finger_joint1",)))
    m = RobotModel(cfg, dtype=torch.float64)
    assert m.opening_range == pytest.approx((0.0, 0.08))
    op, c = m.gripper_state(["panda_finger_joint1"], [0.01])
    assert float(op) == pytest.approx(0.02) and float(c) == pytest.approx(0.25)


# ---------------------------------------------------------------- control points
def test_control_points_move_with_opening(panda: RobotModel) -> None:
    q = panda.sample_q(5, torch.Generator().manual_seed(11))
    P = panda.n_control_points
    assert P == 30
    closed = panda.control_points(q, torch.zeros(5, dtype=torch.float64))
    wide = panda.control_points(q, torch.full((5,), 0.08, dtype=torch.float64))
    assert closed.shape == wide.shape == (5, P, 3)
    # each jaw moves by opening/2 along the closing axis (hand +y expressed in the base frame)
    y_axis = panda.ee_pose(q)[:, :3, 1]
    d = wide - closed
    torch.testing.assert_close(d[:, : P // 2], 0.04 * y_axis[:, None].expand(-1, P // 2, -1), atol=1e-12, rtol=0)
    torch.testing.assert_close(d[:, P // 2 :], -0.04 * y_axis[:, None].expand(-1, P // 2, -1), atol=1e-12, rtol=0)
    # closed jaws coincide; open jaws are 8 cm apart
    torch.testing.assert_close(closed[:, : P // 2], closed[:, P // 2 :], atol=1e-12, rtol=0)
    gap = (wide[:, : P // 2] - wide[:, P // 2 :]).norm(dim=-1)
    torch.testing.assert_close(gap, torch.full_like(gap, 0.08), atol=1e-12, rtol=0)
    # clipped to the physical range
    torch.testing.assert_close(panda.control_points(q, torch.full((5,), 0.2, dtype=torch.float64)), wide)


def test_control_points_lie_on_panda_finger_pads(panda: RobotModel) -> None:
    """With opening = finger1 + finger2 each jaw's points sit on that finger's inner face."""
    q = panda.sample_q(50, torch.Generator().manual_seed(4))
    pts = panda.control_points(q)  # opening from q (mimic finger)
    T = panda.fk(q, links=["panda_leftfinger", "panda_rightfinger"])
    half = panda.n_control_points // 2
    for link, sl in (("panda_leftfinger", slice(0, half)), ("panda_rightfinger", slice(half, None))):
        Ti = torch.linalg.inv(T[link])
        local = pts[:, sl] @ Ti[:, :3, :3].transpose(1, 2) + Ti[:, None, :3, 3]
        # finger mesh (meshes/collision/finger.obj): inner face y = 0, |x| <= 0.0105, 0 <= z <= 0.0539
        assert local[..., 1].abs().max() < 1e-9, link
        assert local[..., 0].abs().max() <= 0.0105
        assert float(local[..., 2].min()) >= 0.0 and float(local[..., 2].max()) <= 0.0539 + 1e-9


def test_control_point_pattern_geometry() -> None:
    cfg = load_robot_config("arx5").control_points
    base, side, axis = control_point_pattern(cfg)
    assert base.shape == (30, 3) and side.shape == (30,)
    torch.testing.assert_close(axis, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    # approach +x: tips at x = tip_offset, jaw extends back by jaw_length; width along a x c = z
    assert float(base[:, 0].max()) == pytest.approx(cfg.tip_offset)
    assert float(base[:, 0].min()) == pytest.approx(cfg.tip_offset - cfg.jaw_length)
    assert float(base[:, 2].max()) == pytest.approx(cfg.jaw_width / 2)
    assert int((side > 0).sum()) == 15


def test_arx5_control_points_follow_ee(arx5: RobotModel) -> None:
    q = arx5.sample_q(8, torch.Generator().manual_seed(9))
    opening = torch.full((8,), 0.05, dtype=torch.float64)
    pts = arx5.control_points(q, opening)
    T = arx5.ee_pose(q)
    local = (pts - T[:, None, :3, 3]) @ T[:, :3, :3]
    torch.testing.assert_close(local, arx5.control_points_ee(opening), atol=1e-12, rtol=0)
    assert float((pts[:, :15].mean(1) - pts[:, 15:].mean(1)).norm(dim=-1).max()) == pytest.approx(0.05)


# ---------------------------------------------------------------- config errors
def test_wrong_names_raise_naming_them() -> None:
    import dataclasses

    cfg = load_robot_config("panda")
    with pytest.raises(ValueError, match="ee_link 'panda_hnd'"):
        RobotModel(dataclasses.replace(cfg, ee_link="panda_hnd"))
    with pytest.raises(ValueError, match="base_link 'nope'"):
        RobotModel(dataclasses.replace(cfg, base_link="nope"))
    with pytest.raises(RobotConfigError, match="arm joint 'panda_joint9'"):
        RobotModel(dataclasses.replace(cfg, arm_joints=("panda_joint1", "panda_joint9")))
    with pytest.raises(RobotConfigError, match="panda_joint7 on the chain"):
        RobotModel(dataclasses.replace(cfg, arm_joints=tuple(f"panda_joint{i}" for i in range(1, 7))))
    with pytest.raises(RobotConfigError, match="mimics 'panda_finger_joint1'"):
        from soma_ros.core.robot_config import GripperConfig

        RobotModel(dataclasses.replace(cfg, gripper=GripperConfig(joints=("panda_finger_joint2",))))
    with pytest.raises(RobotConfigError, match="'gripper' is not a joint"):
        RobotModel(dataclasses.replace(cfg, gripper=GripperConfig(joints=("gripper",))))
    with pytest.raises(ValueError, match="not below base link"):
        RobotModel(dataclasses.replace(cfg, base_link="panda_hand", ee_link="panda_link3", arm_joints=None))


def test_yaml_errors(tmp_path) -> None:
    bad = tmp_path / "r.yaml"
    bad.write_text("urdf: franka_panda/panda.urdf\nee_link: panda_hand\nee_lnk: x\n")
    with pytest.raises(RobotConfigError, match="unknown key 'ee_lnk'"):
        RobotConfig.from_yaml(bad)
    bad.write_text("urdf: franka_panda/panda.urdf\nee_link: panda_hand\ncontrol_points: {count: 20}\n")
    with pytest.raises(RobotConfigError, match="count=20"):
        RobotConfig.from_yaml(bad)
    bad.write_text("urdf: nowhere/robot.urdf\nee_link: panda_hand\n")
    with pytest.raises(FileNotFoundError, match="nowhere/robot.urdf"):
        RobotConfig.from_yaml(bad)
    bad.write_text(
        "urdf: franka_panda/panda.urdf\nee_link: panda_hand\n"
        "control_points: {approach_axis: [0, 0, 1], closing_axis: [0, 1, 1]}\n"
    )
    with pytest.raises(RobotConfigError, match="perpendicular"):
        RobotConfig.from_yaml(bad)


def test_shipped_configs_load() -> None:
    for name in ("panda", "arx5"):
        cfg = load_robot_config(name)
        assert cfg.urdf.is_file() and cfg.control_points.count == 30
        assert math.isclose(sum(x * x for x in cfg.control_points.approach_axis), 1.0)


@pytest.mark.parametrize("name", ["panda", "arx5"])
def test_ee_jacobian_matches_finite_differences(name: str) -> None:
    """Linear rows = d(ee origin)/dq; angular rows = the rotation's rate, checked by central
    differences of the FK on random configurations (float64)."""
    model = RobotModel.from_config(name, dtype=torch.float64)
    q = model.sample_q(5, generator=torch.Generator().manual_seed(3))
    J = model.ee_jacobian(q)
    n = len(model.arm_joint_names)
    assert J.shape == (5, 6, n)
    h = 1e-6
    for j in range(n):
        dq = torch.zeros_like(q)
        dq[:, j] = h
        Tp, Tm = model.ee_pose(q + dq), model.ee_pose(q - dq)
        dp = (Tp[:, :3, 3] - Tm[:, :3, 3]) / (2 * h)
        W = (Tp[:, :3, :3] - Tm[:, :3, :3]) / (2 * h) @ model.ee_pose(q)[:, :3, :3].transpose(1, 2)
        w = torch.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], dim=1)
        torch.testing.assert_close(J[:, :3, j], dp, atol=1e-7, rtol=0)
        torch.testing.assert_close(J[:, 3:, j], w, atol=1e-7, rtol=0)


def test_ee_jacobian_matches_mujoco(panda: RobotModel) -> None:
    """The same URDF in MuJoCo (robot alone, base at the origin): mj_jac at the hand's origin."""
    mujoco = pytest.importorskip("mujoco")
    from soma_ros.world.config import load_robot_config as load_world_robot
    from soma_ros.world.robot import load_robot_spec, rname, attach_robot

    rc = load_world_robot("robot_panda")
    world = mujoco.MjSpec()
    attach_robot(world, load_robot_spec(rc), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    m = world.compile()
    d = mujoco.MjData(m)
    q = panda.sample_q(4, generator=torch.Generator().manual_seed(5))
    J = panda.ee_jacobian(q).numpy()
    adr = [m.jnt_dofadr[m.joint(rname(n)).id] for n in panda.arm_joint_names]
    qadr = [m.jnt_qposadr[m.joint(rname(n)).id] for n in panda.joint_names]
    body = m.body(rname(panda.ee_link)).id
    for b in range(q.shape[0]):
        d.qpos[qadr] = q[b].numpy()
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jp, jr, d.xpos[body], body)
        np.testing.assert_allclose(J[b, :3], jp[:, adr], atol=1e-9)
        np.testing.assert_allclose(J[b, 3:], jr[:, adr], atol=1e-9)


def test_external_wrench_recovers_a_wrench_and_refuses_bad_input(panda: RobotModel) -> None:
    q = panda.sample_q(6, generator=torch.Generator().manual_seed(7))
    names = panda.joint_names + ["panda_finger_joint2"]  # an extra joint is ignored
    pos = torch.cat([q, q[:, -1:]], dim=1)
    w = torch.tensor([[0.3, -0.2, -3.5, 0.05, -0.1, 0.02]], dtype=torch.float64).expand(6, 6)
    tau = (panda.ee_jacobian(q).transpose(1, 2) @ w.unsqueeze(-1)).squeeze(-1)  # [6, 7]
    eff = torch.cat([tau, torch.full((6, len(names) - 7), 12.0, dtype=torch.float64)], dim=1)  # gripper: its force
    torch.testing.assert_close(panda.external_wrench(names, pos, eff), w, atol=1e-9, rtol=0)
    with pytest.raises(ValueError, match="panda_joint3"):
        panda.external_wrench([n for n in names if n != "panda_joint3"], pos[:, 1:], eff[:, 1:])
    bad = eff.clone()
    bad[2, 1] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        panda.external_wrench(names, pos, bad)
