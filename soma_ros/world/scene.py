"""Build the MuJoCo model of one episode: room, table, object, robot, cameras.

The non-robot part is written as MJCF (the object is a ``flexcomp``), the
robot URDF spec is attached under a frame at the configured base pose, and
then the wrist camera, the servos and the grasp constraints are added with
the MjSpec API. :class:`Scene` keeps the compiled model and the indices the
simulation loop, the renderer and the recorder need.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from .config import ObjectConfig, RobotConfig, WorldConfig
from .objects import OBJECT_FLEX_NAME, ObjectGeometry, flexcomp_xml
from .robot import attach_robot, load_robot_spec, rname
from .transforms import MJ_FROM_OPTICAL, look_at_optical, mat_to_quat, quat_to_mat, rpy_to_mat

__all__ = ["Scene", "build_scene", "CAMERA_NAMES", "optical_frame_id", "wrist_mount_transform"]

#: Camera names, in recording order.
CAMERA_NAMES = ("cam_wrist", "cam_front", "cam_side")
#: solref of the grasp's connect equalities (hand -> each held object vertex): a soft pin, 10 ms time constant
GRASP_SOLREF = (0.01, 1.0)


def optical_frame_id(cam: str) -> str:
    """The tf frame of a camera's colour optical frame, e.g. ``cam_front_color_optical_frame``."""
    return f"{cam}_color_optical_frame"


def wrist_mount_transform(rc: RobotConfig) -> np.ndarray:
    """[4, 4] pose of the wrist optical frame in the wrist camera's parent link (from config)."""
    wc = rc.wrist_camera
    if wc.rpy is not None:
        R = rpy_to_mat(wc.rpy)
    else:
        R = look_at_optical(wc.xyz, wc.look_at, wc.up)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = wc.xyz
    return T


def _fmt(v) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.asarray(v).ravel())


@dataclass
class Scene:
    """A compiled episode model and the indices into it.

    Arrays: ``arm_qadr``/``arm_dadr`` [n_arm], ``grip_qadr``/``grip_dadr``
    [n_grip] (URDF order of ``gripper.joints``), ``vert_body`` [N] body id of
    each object vertex, ``vert_dadr`` [N, 3] its slide dofs (world x, y, z),
    ``grasp_eq`` [N] the (inactive) connect equality hand -> vertex i,
    ``robot_geom`` [ngeom] bool mask of robot geoms (for the robot mask).
    """

    model: mujoco.MjModel
    data: mujoco.MjData
    cfg: WorldConfig
    robot: RobotConfig
    obj_cfg: ObjectConfig
    geometry: ObjectGeometry
    arm_qadr: np.ndarray
    arm_dadr: np.ndarray
    grip_qadr: np.ndarray
    grip_dadr: np.ndarray
    act_grip_pos: int
    act_grip_vel: int
    hand_body: int
    flex_id: int
    vert_body: np.ndarray
    vert_dadr: np.ndarray
    vert_mass: np.ndarray
    grasp_eq: np.ndarray
    robot_geom: np.ndarray
    table_geom: int
    camera_ids: dict[str, int]
    base_T: np.ndarray  # [4, 4] world <- base_link
    wrist_T: np.ndarray  # [4, 4] wrist parent link <- cam_wrist optical
    camera_T: dict[str, np.ndarray] = field(default_factory=dict)  # fixed cameras, world <- optical
    young: float = 0.0
    mass: float = 0.0
    table_friction: float = 0.0

    def vertex_positions(self) -> np.ndarray:
        """Object vertex positions [N, 3] in `world` (valid after mj_forward)."""
        f = self.flex_id
        a = self.model.flex_vertadr[f]
        return self.data.flexvert_xpos[a : a + self.model.flex_vertnum[f]].copy()

    def vertex_velocities(self) -> np.ndarray:
        """Object vertex velocities [N, 3] in `world` from their slide dofs."""
        return self.data.qvel[self.vert_dadr]


def _world_mjcf(cfg: WorldConfig, geom: ObjectGeometry, obj: ObjectConfig, young: float, mass: float,
                table_friction: float, width: int, height: int) -> str:
    t = cfg.table
    top = t.height
    hx, hy, th = t.size[0] / 2, t.size[1] / 2, t.size[2] / 2
    cx, cy = t.center_xy
    cams = []
    for name, fc in cfg.cameras.fixed.items():
        R = look_at_optical(fc.position, fc.look_at, fc.up) @ MJ_FROM_OPTICAL
        cams.append(
            f'<camera name="{name}" pos="{_fmt(fc.position)}" quat="{_fmt(mat_to_quat(R))}" fovy="{cfg.cameras.fovy_deg:.6g}"/>'
        )
    legs = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            lx, ly = cx + sx * (hx - 0.05), cy + sy * (hy - 0.05)
            legs.append(
                f'<geom type="box" size="0.03 0.03 {(top - 2 * th) / 2:.6g}" pos="{lx:.6g} {ly:.6g} {(top - 2 * th) / 2:.6g}" '
                f'rgba="0.35 0.3 0.25 1" contype="0" conaffinity="0"/>'
            )
    material = None
    assets = ""
    if obj.kind == "cloth":
        c1, c2 = np.asarray(obj.rgba[:3]), np.array([0.95, 0.92, 0.85])
        assets = (
            f'<texture name="object_tex" type="2d" builtin="checker" rgb1="{_fmt(c1)}" rgb2="{_fmt(c2)}" width="256" height="256"/>'
            '<material name="object_mat" texture="object_tex" texrepeat="4 4"/>'
        )
        material = "object_mat"
    elif obj.kind == "doll":
        c1, c2 = np.asarray(obj.rgba[:3]), np.array([0.96, 0.8, 0.66])
        # 2x2 checker: u < 0.5 -> body colour (the object's rgba), u > 0.5 -> head (skin) colour, at v = 0.25.
        assets = (
            f'<texture name="object_tex" type="2d" builtin="checker" rgb1="{_fmt(c1)}" rgb2="{_fmt(c2)}" width="64" height="64"/>'
            '<material name="object_mat" texture="object_tex" texrepeat="1 1"/>'
        )
        material = "object_mat"
    p = cfg.physics
    return f"""
<mujoco model="soma_reference_world">
  <option timestep="{p.timestep:.12g}" integrator="{p.integrator}" solver="{p.solver}" iterations="{p.iterations}"
          ls_iterations="{p.ls_iterations}" cone="elliptic"/>
  <visual>
    <global offwidth="{max(width, 640)}" offheight="{max(height, 480)}"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.45 0.45 0.45" specular="0.05 0.05 0.05"/>
    <quality shadowsize="0"/>
  </visual>
  <asset>
    <texture name="floor_tex" type="2d" builtin="checker" rgb1="0.42 0.42 0.44" rgb2="0.38 0.38 0.40" width="256" height="256"/>
    <material name="floor_mat" texture="floor_tex" texrepeat="8 8"/>
    {assets}
  </asset>
  <worldbody>
    <light name="key" pos="0.6 -0.4 2.4" dir="-0.1 0.2 -1" directional="false" castshadow="false" diffuse="0.55 0.55 0.55"/>
    <light name="fill" pos="-0.5 0.8 2.2" dir="0.4 -0.3 -1" directional="false" castshadow="false" diffuse="0.3 0.3 0.3"/>
    <geom name="floor" type="plane" size="3 3 0.1" material="floor_mat" contype="1" conaffinity="1"/>
    <geom name="wall_back" type="box" size="0.02 3 1.5" pos="-1.4 0 1.5" rgba="0.78 0.78 0.75 1" contype="0" conaffinity="0"/>
    <geom name="wall_front" type="box" size="0.02 3 1.5" pos="2.4 0 1.5" rgba="0.74 0.76 0.78 1" contype="0" conaffinity="0"/>
    <geom name="wall_left" type="box" size="3 0.02 1.5" pos="0.5 1.9 1.5" rgba="0.76 0.75 0.72 1" contype="0" conaffinity="0"/>
    <geom name="wall_right" type="box" size="3 0.02 1.5" pos="0.5 -1.9 1.5" rgba="0.72 0.74 0.76 1" contype="0" conaffinity="0"/>
    <geom name="table" type="box" size="{hx:.6g} {hy:.6g} {th:.6g}" pos="{cx:.6g} {cy:.6g} {top - th:.9g}"
          rgba="{_fmt(t.rgba)}" priority="1" condim="6" friction="{table_friction:.6g} 0.005 {t.rolling_friction:.6g}"
          solref="0.005 1" solimp="0.95 0.99 0.001" contype="1" conaffinity="1"/>
    {''.join(legs)}
    {''.join(cams)}
    {flexcomp_xml(geom, obj, young=young, mass=mass, material=material)}
  </worldbody>
</mujoco>
"""


def build_scene(
    cfg: WorldConfig,
    obj: ObjectConfig,
    geom: ObjectGeometry,
    width: int,
    height: int,
    young: float,
    mass: float,
    table_friction: float,
) -> Scene:
    """Compile the episode model. ``young``/``mass``/``table_friction`` already include effects."""
    rc = cfg.robot_config
    assert rc is not None
    spec = mujoco.MjSpec.from_string(_world_mjcf(cfg, geom, obj, young, mass, table_friction, width, height))
    yaw = np.radians(cfg.robot_base_yaw_deg)
    base_quat = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
    base_pos = np.asarray(cfg.robot_base_xyz, float)
    attach_robot(spec, load_robot_spec(rc), base_pos, base_quat)

    # Wrist camera on its parent link.
    wrist_T = wrist_mount_transform(rc)
    cam_quat = mat_to_quat(wrist_T[:3, :3] @ MJ_FROM_OPTICAL)
    spec.body(rname(rc.wrist_camera.parent)).add_camera(
        name="cam_wrist", pos=list(wrist_T[:3, 3]), quat=list(cam_quat), fovy=cfg.cameras.fovy_deg
    )

    # The arm has no actuators: it is driven kinematically along the plan (see simulate.py).
    g = rc.gripper
    ga = spec.add_actuator(name="gripper_pos", target=rname(g.actuated), trntype=mujoco.mjtTrn.mjTRN_JOINT)
    ga.set_to_position(kp=g.kp)
    ga.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    ga.forcerange = [-g.force_limit, g.force_limit]
    gv = spec.add_actuator(name="gripper_vel", target=rname(g.actuated), trntype=mujoco.mjtTrn.mjTRN_JOINT)
    gv.set_to_velocity(kv=g.kv)

    # Grasp: one inactive connect equality hand -> each object vertex body.
    n_vert = len(geom.points)
    for i in range(n_vert):
        e = spec.add_equality(
            name=f"grasp_{i}",
            type=mujoco.mjtEq.mjEQ_CONNECT,
            objtype=mujoco.mjtObj.mjOBJ_BODY,
            name1=rname(rc.hand_link),
            name2=f"{OBJECT_FLEX_NAME}_{i}",
        )
        e.active = False
        e.solref = list(GRASP_SOLREF)

    model = spec.compile()
    data = mujoco.MjData(model)
    return _index(model, data, cfg, rc, obj, geom, base_pos, base_quat, wrist_T, young, mass, table_friction)


def _index(model, data, cfg, rc, obj, geom, base_pos, base_quat, wrist_T, young, mass, table_friction) -> Scene:
    m = model
    jid = lambda n: m.joint(rname(n)).id  # noqa: E731
    arm_qadr = np.array([m.jnt_qposadr[jid(n)] for n in rc.arm_joints])
    arm_dadr = np.array([m.jnt_dofadr[jid(n)] for n in rc.arm_joints])
    grip_qadr = np.array([m.jnt_qposadr[jid(n)] for n in rc.gripper.joints])
    grip_dadr = np.array([m.jnt_dofadr[jid(n)] for n in rc.gripper.joints])
    # Every non-actuated gripper joint must follow the actuated one through a joint equality (URDF mimic).
    act = jid(rc.gripper.actuated)
    for n in rc.gripper.joints:
        if n == rc.gripper.actuated:
            continue
        j = jid(n)
        ok = any(
            m.eq_type[e] == mujoco.mjtEq.mjEQ_JOINT and {m.eq_obj1id[e], m.eq_obj2id[e]} == {j, act}
            for e in range(m.neq)
        )
        if not ok:
            raise ValueError(f"robot {rc.name}: gripper joint {n} is neither actuated nor a <mimic> of {rc.gripper.actuated}")
    act_id = lambda n: m.actuator(n).id  # noqa: E731
    f = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_FLEX, OBJECT_FLEX_NAME)
    if f < 0:
        raise RuntimeError("object flex missing from the compiled model")
    va, vn = m.flex_vertadr[f], m.flex_vertnum[f]
    vert_body = m.flex_vertbodyid[va : va + vn].copy()
    vert_dadr = np.zeros((vn, 3), dtype=int)
    for i, b in enumerate(vert_body):
        if m.body(b).name != f"{OBJECT_FLEX_NAME}_{i}":
            raise RuntimeError(f"flex vertex {i} is on body {m.body(b).name}, expected {OBJECT_FLEX_NAME}_{i}")
        if m.body_dofnum[b] != 3:
            raise RuntimeError(f"flex vertex body {m.body(b).name} has {m.body_dofnum[b]} dofs, expected 3 slides")
        d0 = m.body_dofadr[b]
        for k in range(3):
            jnt = m.dof_jntid[d0 + k]
            axis = quat_to_mat(m.body_quat[b]) @ m.jnt_axis[jnt]
            if m.jnt_type[jnt] != mujoco.mjtJoint.mjJNT_SLIDE or not np.allclose(np.abs(axis), np.eye(3)[k], atol=1e-9):
                raise RuntimeError(f"flex vertex body {m.body(b).name}: dof {k} is not a world-aligned slide")
        vert_dadr[i] = np.arange(d0, d0 + 3)
    grasp_eq = np.array([m.equality(f"grasp_{i}").id for i in range(vn)])
    base_id = m.body(rname(rc.base_link)).id
    robot_geom = np.array([m.body_rootid[m.geom_bodyid[g]] == base_id for g in range(m.ngeom)], bool)
    cams = {n: m.camera(n).id for n in CAMERA_NAMES}
    # Clip planes: near 2 cm (wrist camera sees the fingers at ~5 cm), far 12 m.
    m.vis.map.znear = 0.02 / m.stat.extent
    m.vis.map.zfar = 12.0 / m.stat.extent
    base_T = np.eye(4)
    base_T[:3, :3] = quat_to_mat(base_quat)
    base_T[:3, 3] = base_pos
    camera_T = {}
    for name, fc in cfg.cameras.fixed.items():
        T = np.eye(4)
        T[:3, :3] = look_at_optical(fc.position, fc.look_at, fc.up)
        T[:3, 3] = fc.position
        camera_T[name] = T
    return Scene(
        model=m,
        data=data,
        cfg=cfg,
        robot=rc,
        obj_cfg=obj,
        geometry=geom,
        arm_qadr=arm_qadr,
        arm_dadr=arm_dadr,
        grip_qadr=grip_qadr,
        grip_dadr=grip_dadr,
        act_grip_pos=act_id("gripper_pos"),
        act_grip_vel=act_id("gripper_vel"),
        hand_body=m.body(rname(rc.hand_link)).id,
        flex_id=f,
        vert_body=vert_body,
        vert_dadr=vert_dadr,
        vert_mass=m.body_mass[vert_body].copy(),
        grasp_eq=grasp_eq,
        robot_geom=robot_geom,
        table_geom=m.geom("table").id,
        camera_ids=cams,
        base_T=base_T,
        wrist_T=wrist_T,
        camera_T=camera_T,
        young=young,
        mass=mass,
        table_friction=table_friction,
    )
