"""URDF validation: broken files give one-line errors naming the element; axis/mimic semantics."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import yourdfpy

from soma_ros.core.robot import RobotModel
from soma_ros.core.robot_config import RobotConfig
from soma_ros.core.robot_urdf import URDFError, parse_urdf

torch.set_num_threads(1)

TWO_LINK = """<robot name="two">
  <link name="base"/>
  <link name="l1"/>
  <link name="l2"/>
  <link name="tip"/>
  <joint name="j1" type="revolute">
    <origin xyz="0 0 0.1" rpy="0.1 0.2 0.3"/>
    <parent link="base"/><child link="l1"/>
    {axis1}
    <limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
  <joint name="j2" type="{type2}">
    <origin xyz="0.3 0 0" rpy="0 0.4 0"/>
    <parent link="l1"/><child link="l2"/>
    <axis xyz="0 1 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
    {mimic2}
  </joint>
  <joint name="jt" type="fixed">
    <origin xyz="0.1 0 0"/>
    <parent link="l2"/><child link="{tip_child}"/>
  </joint>
</robot>
"""


def _urdf(tmp_path, axis1: str = '<axis xyz="0 0 1"/>', type2: str = "revolute", mimic2: str = "", tip_child: str = "tip"):
    p = tmp_path / "two.urdf"
    p.write_text(TWO_LINK.format(axis1=axis1, type2=type2, mimic2=mimic2, tip_child=tip_child))
    return p


def _model(path, ee: str = "tip") -> RobotModel:
    return RobotModel(RobotConfig(urdf=path, ee_link=ee), dtype=torch.float64)


def _check_against_yourdfpy(model: RobotModel, n: int = 50) -> None:
    robot = yourdfpy.URDF.load(str(model.config.urdf), load_meshes=False, build_collision_scene_graph=False,
                               load_collision_meshes=False)
    q = model.sample_q(n, torch.Generator().manual_seed(0))
    T = model.ee_pose(q).numpy()
    for i in range(n):
        robot.update_cfg(dict(zip(model.joint_names, q[i].tolist())))
        ref = robot.get_transform(model.ee_link, model.base_link)
        assert np.abs(T[i] - ref).max() < 1e-6


def test_missing_axis_defaults_to_x(tmp_path) -> None:
    """URDF spec: a movable joint without <axis> turns about +x (pytorch_kinematics alone would use +z)."""
    m = _model(_urdf(tmp_path, axis1=""))
    assert m.urdf.joints["j1"].axis == (1.0, 0.0, 0.0)
    _check_against_yourdfpy(m)


def test_mimic_with_multiplier_and_offset(tmp_path) -> None:
    m = _model(_urdf(tmp_path, mimic2='<mimic joint="j1" multiplier="-0.5" offset="0.2"/>'))
    assert m.joint_names == ["j1"]
    full = m.full_joint_vector(torch.tensor([[0.6]], dtype=torch.float64))
    torch.testing.assert_close(full, torch.tensor([[0.6, -0.5 * 0.6 + 0.2]], dtype=torch.float64))
    _check_against_yourdfpy(m)


def test_continuous_and_prismatic(tmp_path) -> None:
    m = _model(_urdf(tmp_path, type2="prismatic"))
    _check_against_yourdfpy(m)
    m = _model(_urdf(tmp_path, type2="continuous"))
    lo, hi = m.joint_limits()
    assert torch.isinf(lo[1]) and torch.isinf(hi[1])
    _check_against_yourdfpy(m)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"tip_child": "tipp"}, "joint 'jt' names child link 'tipp', which is not defined"),
        ({"type2": "floating"}, "joint 'j2' has type 'floating'"),
        ({"type2": "spherical"}, "joint 'j2' has unknown type 'spherical'"),
        ({"axis1": '<axis xyz="0 0 0"/>'}, "joint 'j1' has a zero-length <axis>"),
        ({"axis1": '<axis xyz="0 zero 1"/>'}, r"joint 'j1' <axis xyz> must be 3 numbers"),
        ({"mimic2": '<mimic joint="j7"/>'}, "joint 'j2' mimics joint 'j7', which is not defined"),
        ({"tip_child": "l1"}, "link 'l1' is the child of two joints"),
    ],
)
def test_broken_urdf_names_the_element(tmp_path, kwargs, match) -> None:
    with pytest.raises(URDFError, match=match) as info:
        _model(_urdf(tmp_path, **kwargs))
    assert "\n" not in str(info.value)


def test_malformed_xml_and_structure(tmp_path) -> None:
    p = tmp_path / "bad.urdf"
    p.write_text('<robot name="x"><link name="a"><joint name="j" type="fixed"></robot>')
    with pytest.raises(URDFError, match=r"bad.urdf: malformed XML \(mismatched tag: line 1"):
        parse_urdf(p)
    p.write_text('<robot name="x"><link name="a"/><link name="b"/></robot>')
    with pytest.raises(URDFError, match="2 root links"):
        parse_urdf(p)
    p.write_text('<sdf><link name="a"/></sdf>')
    with pytest.raises(URDFError, match="expected <robot>"):
        parse_urdf(p)
    p.write_text(
        '<robot name="x"><link name="a"/><link name="b"/>'
        '<joint name="j" type="revolute"><parent link="a"/><child link="b"/></joint></robot>'
    )
    with pytest.raises(URDFError, match="joint 'j' \\(revolute\\) has no <limit>"):
        parse_urdf(p)
    p.write_text(
        '<robot name="x"><link name="a"/><link name="b"/><link name="c"/>'
        '<joint name="j1" type="revolute"><parent link="a"/><child link="b"/><limit lower="0" upper="1"/>'
        '<mimic joint="j2"/></joint>'
        '<joint name="j2" type="revolute"><parent link="b"/><child link="c"/><limit lower="0" upper="1"/>'
        '<mimic joint="j1"/></joint></robot>'
    )
    with pytest.raises(URDFError, match="mimic cycle"):
        parse_urdf(p)
    with pytest.raises(FileNotFoundError):
        parse_urdf(tmp_path / "missing.urdf")


def test_shipped_urdfs_parse() -> None:
    from soma_ros.paths import ROBOTS_DIR

    panda = parse_urdf(ROBOTS_DIR / "franka_panda" / "panda.urdf")
    assert panda.root == "panda_link0"
    assert panda.joints["panda_finger_joint2"].mimic is not None
    assert panda.mimic_followers("panda_finger_joint1") == ["panda_finger_joint2"]
    arx = parse_urdf(ROBOTS_DIR / "arx5" / "X5.urdf")
    assert [j.name for j in arx.path_joints("base_link", "eef_link")][-1] == "gripper_fixed_joint"
