"""Configuration of the reference world, as dataclasses loaded from YAML.

Files (all under ``config/world/`` unless a path is given):

* ``default.yaml``   scene, cameras, physics, objects, tasks, presets
  (:class:`WorldConfig`); it names the robot YAML and the effects YAML.
* ``robot_panda.yaml`` the robot (:class:`RobotConfig`): URDF, links, joints,
  gripper actuation, wrist-camera mount, controller gains.
* ``effects.yaml``   magnitudes of the switchable physical effects
  (:class:`EffectsConfig`).

Every loader rejects unknown keys with a one-line error naming the key, so a
typo in a YAML never silently falls back to a default.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Union, get_args, get_origin, get_type_hints


from ..paths import ROBOTS_DIR, resolve_config
from ..core.config import read_config

__all__ = [
    "PhysicsConfig",
    "TableConfig",
    "FixedCameraConfig",
    "WristCameraConfig",
    "CameraRigConfig",
    "GripperConfig",
    "RobotConfig",
    "ObjectConfig",
    "PresetConfig",
    "WindConfig",
    "AirDragConfig",
    "TableFrictionConfig",
    "SlipConfig",
    "StiffConfig",
    "HeavyConfig",
    "EffectsConfig",
    "WorldConfig",
    "load_world_config",
    "load_robot_config",
    "load_effects_config",
    "OBJECTS",
    "TASKS",
    "EFFECTS",
]

#: Objects the world can simulate.
OBJECTS = ("rope", "cloth", "doll")
#: Manipulation tasks: ``lift`` = grasp-and-lift, ``drag`` = grasp and drag on the
#: table, ``fold`` = grasp one side of a cloth and lay it over the other, ``drop`` =
#: lift as ``lift`` does, then open the fingers: the object falls back onto the table.
TASKS = ("lift", "drag", "fold", "drop")
#: Switchable physical effects (all off by default).
EFFECTS = ("wind", "air_drag", "table_friction", "slip", "stiff", "heavy")


# --------------------------------------------------------------------------- helpers


def _from_dict(cls: type, data: Any, where: str) -> Any:
    """Build dataclass ``cls`` from a YAML mapping, recursively, rejecting unknown keys."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a mapping, got {type(data).__name__}")
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(names)}")
    kwargs = {}
    for key, value in data.items():
        kwargs[key] = _coerce(hints[key], value, f"{where}.{key}")
    try:
        return cls(**kwargs)
    except TypeError as exc:  # missing required fields
        raise ValueError(f"{where}: {exc}") from None


def _coerce(tp: Any, value: Any, where: str) -> Any:
    origin = get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return _from_dict(tp, value, where)
    if origin is Union:
        args = [a for a in get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(args[0], value, where)
    if origin is dict:
        _, vt = get_args(tp)
        if not isinstance(value, dict):
            raise ValueError(f"{where}: expected a mapping")
        return {str(k): _coerce(vt, v, f"{where}.{k}") for k, v in value.items()}
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{where}: expected a list, got {value!r}")
        args = get_args(tp)
        et = args[0] if args else Any
        out = [_coerce(et, v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where}: expected true/false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ValueError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def _read_yaml(path: Path) -> dict:
    return read_config(path)


def _vec(v: list[float], n: int, where: str) -> None:
    if len(v) != n:
        raise ValueError(f"{where}: expected {n} numbers, got {len(v)}")


# --------------------------------------------------------------------------- robot


@dataclass
class GripperConfig:
    """A parallel gripper driven through one actuated joint.

    ``joints`` are all gripper joints recorded on /joint_states (URDF names).
    ``actuated`` is the joint that gets a position servo; every other gripper
    joint must be a ``<mimic>`` of it in the URDF (MuJoCo's URDF compiler turns
    mimics into joint equalities). ``joint_per_width`` maps the finger gap
    (metres between the pads) to the actuated joint value:
    ``q = joint_offset + joint_per_width * gap``.
    """

    joints: list[str]
    actuated: str
    open_gap: float = 0.08
    joint_per_width: float = 0.5
    joint_offset: float = 0.0
    kp: float = 2000.0
    kv: float = 40.0
    force_limit: float = 40.0


@dataclass
class WristCameraConfig:
    """Pose of ``cam_wrist_color_optical_frame`` relative to ``parent`` (a robot link).

    Orientation either from ``rpy`` (of the optical frame, radians) or from
    ``look_at`` (a point in the parent frame) with ``up`` (parent-frame
    direction that points up in the image).
    """

    parent: str
    xyz: list[float]
    look_at: Optional[list[float]] = None
    up: Optional[list[float]] = None
    rpy: Optional[list[float]] = None


#: What /joint_states effort carries (robot YAML ``effort``; soma_ros.world.simulate).
EFFORT_MODES = ("external", "none")


@dataclass
class RobotConfig:
    """An arm with a parallel gripper, described by a URDF loaded unchanged."""

    name: str
    urdf: str
    base_link: str
    hand_link: str
    arm_joints: list[str]
    gripper: GripperConfig
    wrist_camera: WristCameraConfig
    #: TCP (centre between the finger pads) in the hand-link frame, metres.
    tcp_offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.1])
    #: Hand-frame axis pointing from the hand towards the fingertips.
    approach_axis: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.0])
    #: Hand-frame axis along which the fingers close.
    closing_axis: list[float] = field(default_factory=lambda: [0.0, 1.0, 0.0])
    #: Null-space posture for IK (one value per arm joint, radians).
    rest_posture: list[float] = field(default_factory=list)
    #: Links whose geoms may touch the object (the hand and the fingers).
    contact_links: list[str] = field(default_factory=list)
    #: Geom colour of the robot (the URDF's visual materials are not loaded).
    rgba: list[float] = field(default_factory=lambda: [0.92, 0.92, 0.92, 1.0])
    #: /joint_states effort: "external" (the arm's external joint torques, N m, as a torque-sensing
    #: arm estimates them after its own gravity model, and the gripper servo's force, N) or "none"
    #: (empty: a rig without torque sensing). See soma_ros.world.simulate.
    effort: str = "external"
    #: Standard deviation of the Gaussian noise on every effort sample (N m for the arm, N for the gripper).
    effort_noise: float = 0.05
    #: Directory of this robot YAML (filled in by the loader).
    source_dir: str = ""

    def urdf_path(self) -> Path:
        """The URDF as an absolute path (relative names resolve against the robots data dir)."""
        p = Path(self.urdf)
        for cand in (p, Path(self.source_dir) / p, ROBOTS_DIR / p):
            if cand.is_file():
                return cand.resolve()
        raise FileNotFoundError(f"robot URDF not found: {self.urdf} (looked in ., {self.source_dir}, {ROBOTS_DIR})")

    def validate(self) -> None:
        if not self.arm_joints:
            raise ValueError(f"robot {self.name}: arm_joints is empty")
        if self.rest_posture and len(self.rest_posture) != len(self.arm_joints):
            raise ValueError(
                f"robot {self.name}: rest_posture has {len(self.rest_posture)} values for {len(self.arm_joints)} arm joints"
            )
        if self.gripper.actuated not in self.gripper.joints:
            raise ValueError(f"robot {self.name}: gripper.actuated {self.gripper.actuated} is not in gripper.joints")
        if self.effort not in EFFORT_MODES:
            raise ValueError(f"robot {self.name}: effort must be one of {', '.join(EFFORT_MODES)}, got {self.effort!r}")
        if not (math.isfinite(float(self.effort_noise)) and float(self.effort_noise) >= 0.0):
            raise ValueError(f"robot {self.name}: effort_noise must be >= 0 (N m / N), got {self.effort_noise}")
        _vec(self.tcp_offset, 3, f"robot {self.name}: tcp_offset")
        _vec(self.approach_axis, 3, f"robot {self.name}: approach_axis")
        _vec(self.closing_axis, 3, f"robot {self.name}: closing_axis")
        if abs(float(sum(a * b for a, b in zip(self.approach_axis, self.closing_axis)))) > 1e-6:
            raise ValueError(f"robot {self.name}: approach_axis and closing_axis must be orthogonal")
        wc = self.wrist_camera
        _vec(wc.xyz, 3, "wrist_camera.xyz")
        if (wc.rpy is None) == (wc.look_at is None):
            raise ValueError("wrist_camera: give exactly one of rpy or look_at (+ up)")
        if wc.look_at is not None and wc.up is None:
            raise ValueError("wrist_camera: look_at needs up")


def load_robot_config(path: Union[str, Path]) -> RobotConfig:
    """Load and validate a robot YAML (a path, or a name under config/world/)."""
    p = resolve_config(path if str(path).endswith(".yaml") or Path(path).is_file() else f"world/{path}")
    cfg = _from_dict(RobotConfig, _read_yaml(p), p.name)
    cfg.source_dir = str(p.parent)
    cfg.validate()
    return cfg


# --------------------------------------------------------------------------- scene


@dataclass
class PhysicsConfig:
    timestep: float = 1.0 / 480.0
    integrator: str = "discrete"
    solver: str = "Newton"
    iterations: int = 50
    ls_iterations: int = 20
    #: Seconds simulated before the first recorded frame (object settles).
    settle_seconds: float = 0.4
    #: An object element (rope segment, cloth or tet edge) longer than this many times its rest
    #: length after a frame means the simulation exploded: the episode is rejected with an error
    #: instead of recording it (ropes that fall off the table stretch up to ~1.8x on impact).
    max_element_stretch: float = 3.0


@dataclass
class TableConfig:
    #: Height of the table top in `world` (metres). Recorded in the sidecar only.
    height: float = 0.75
    #: Full extents of the table top (x, y) and its thickness (metres).
    size: list[float] = field(default_factory=lambda: [0.9, 1.2, 0.04])
    center_xy: list[float] = field(default_factory=lambda: [0.45, 0.0])
    friction: float = 0.8
    #: Rolling friction (condim 6 on the table) keeps a pushed rope from rolling away.
    rolling_friction: float = 0.002
    rgba: list[float] = field(default_factory=lambda: [0.55, 0.45, 0.35, 1.0])


@dataclass
class FixedCameraConfig:
    position: list[float]
    look_at: list[float]
    up: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.0])


@dataclass
class CameraRigConfig:
    """The three cameras: ``cam_wrist`` (mount in the robot YAML) and the fixed ones."""

    #: Vertical field of view of all colour cameras (degrees); square pixels.
    fovy_deg: float = 58.0
    fixed: dict[str, FixedCameraConfig] = field(default_factory=dict)
    #: Depth outside [min_m, max_m] is recorded as 0 (no depth), like a RealSense.
    depth_min_m: float = 0.04
    depth_max_m: float = 3.0


@dataclass
class ObjectConfig:
    """One deformable object. Lengths in metres, mass in kg, moduli in Pa."""

    kind: str  # rope | cloth | doll
    mass: float
    young: float
    poisson: float = 0.3
    damping: float = 0.002
    radius: float = 0.005
    friction: float = 0.8
    rgba: list[float] = field(default_factory=lambda: [0.8, 0.2, 0.2, 1.0])
    # rope
    length: float = 0.35
    segments: int = 24
    max_bend: float = 0.6
    # cloth
    size: list[float] = field(default_factory=lambda: [0.24, 0.24])
    count: list[int] = field(default_factory=lambda: [13, 13])
    thickness: float = 0.002
    # doll
    scale: float = 1.0
    spacing: float = 0.014
    # grasp
    #: TCP height above the table top when closing (metres).
    grasp_height: float = 0.01
    #: Finger gap commanded when closed (metres).
    grasp_gap: float = 0.01
    #: Vertices within this distance of the TCP are held by the grasp (metres).
    grasp_radius: float = 0.02
    #: At most this many vertices are held.
    grasp_max_vertices: int = 12
    #: Placement: centre of the object is drawn in workspace_x/y (world metres).
    workspace_x: list[float] = field(default_factory=lambda: [0.45, 0.58])
    workspace_y: list[float] = field(default_factory=lambda: [-0.1, 0.1])


@dataclass
class PresetConfig:
    episodes: int
    frames: list[int]  # [min, max] inclusive, drawn per episode
    width: int
    height: int
    split_ratio: float = 0.7


@dataclass
class TaskMotionConfig:
    """Sizes of the scripted motions (metres), drawn uniformly per episode."""

    hover_height: list[float] = field(default_factory=lambda: [0.08, 0.14])
    lift_height: list[float] = field(default_factory=lambda: [0.12, 0.2])
    drag_distance: list[float] = field(default_factory=lambda: [0.08, 0.16])
    drag_lift: float = 0.015
    fold_lift: list[float] = field(default_factory=lambda: [0.06, 0.1])


@dataclass
class ContactSheetConfig:
    frames: int = 4
    tile_width: int = 160


# --------------------------------------------------------------------------- effects


@dataclass
class WindConfig:
    """Aerodynamic pressure drag of the object's elements relative to a steady wind."""

    velocity: list[float] = field(default_factory=lambda: [0.0, 6.0, 0.0])
    air_density: float = 1.2
    drag_coefficient: float = 1.2
    #: When the wind starts: None blows from the first step after settling; a number in [0, 1] is a
    #: fraction of the carrying phase (a fan switched on mid-task: a resting object is not blown
    #: off the table before the robot takes it).
    onset: Optional[float] = None

    def __post_init__(self) -> None:
        if self.onset is not None and not 0.0 <= float(self.onset) <= 1.0:
            raise ValueError(f"effects.wind.onset must be null or in [0, 1] (a fraction of the carry), got {self.onset}")


@dataclass
class AirDragConfig:
    """Pressure drag in still air, with an exaggerated density (visible at hand speeds)."""

    density: float = 150.0
    drag_coefficient: float = 1.2


@dataclass
class TableFrictionConfig:
    friction: float = 0.1


@dataclass
class SlipConfig:
    """The grasp slips: at ``onset`` (fraction of the carrying phase) most held vertices let go."""

    onset: float = 0.4
    keep_fraction: float = 0.34
    #: Softer constraint reference (time constant s, damping ratio) for the vertices still held.
    solref: list[float] = field(default_factory=lambda: [0.08, 1.0])


@dataclass
class StiffConfig:
    young_scale: float = 10.0


@dataclass
class HeavyConfig:
    mass_scale: float = 3.0


@dataclass
class EffectsConfig:
    wind: WindConfig = field(default_factory=WindConfig)
    air_drag: AirDragConfig = field(default_factory=AirDragConfig)
    table_friction: TableFrictionConfig = field(default_factory=TableFrictionConfig)
    slip: SlipConfig = field(default_factory=SlipConfig)
    stiff: StiffConfig = field(default_factory=StiffConfig)
    heavy: HeavyConfig = field(default_factory=HeavyConfig)

    def magnitudes(self, names: list[str]) -> dict[str, dict]:
        """{effect: its magnitude parameters} for the given effect names."""
        return {n: dataclasses.asdict(getattr(self, n)) for n in names}


def load_effects_config(path: Union[str, Path]) -> EffectsConfig:
    p = resolve_config(path if str(path).endswith(".yaml") or Path(path).is_file() else f"world/{path}")
    return _from_dict(EffectsConfig, _read_yaml(p), p.name)


# --------------------------------------------------------------------------- world


@dataclass
class WorldConfig:
    """Everything the reference world needs to generate a dataset."""

    robot: str = "robot_panda"
    effects_config: str = "effects"
    fps: float = 30.0
    #: Stamps start at this epoch (s) + a seed-dependent offset.
    epoch_sec: int = 1_700_000_000
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    table: TableConfig = field(default_factory=TableConfig)
    robot_base_xyz: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.75])
    robot_base_yaw_deg: float = 0.0
    cameras: CameraRigConfig = field(default_factory=CameraRigConfig)
    objects: dict[str, ObjectConfig] = field(default_factory=dict)
    tasks: dict[str, list[str]] = field(default_factory=dict)
    motion: TaskMotionConfig = field(default_factory=TaskMotionConfig)
    presets: dict[str, PresetConfig] = field(default_factory=dict)
    contact_sheet: ContactSheetConfig = field(default_factory=ContactSheetConfig)
    # Filled by the loader / caller (not YAML keys):
    robot_config: Optional[RobotConfig] = None
    effects: Optional[EffectsConfig] = None

    def validate(self) -> None:
        for name in ("cam_front", "cam_side"):
            if name not in self.cameras.fixed:
                raise ValueError(f"world config: cameras.fixed must define {name}")
        for name, obj in self.objects.items():
            if name not in OBJECTS:
                raise ValueError(f"world config: unknown object '{name}' (known: {', '.join(OBJECTS)})")
            if obj.kind != name:
                raise ValueError(f"world config: objects.{name}.kind must be '{name}'")
        for name, tasks in self.tasks.items():
            for t in tasks:
                if t not in TASKS:
                    raise ValueError(f"world config: tasks.{name} has unknown task '{t}' (known: {', '.join(TASKS)})")
            if "fold" in tasks and name != "cloth":
                raise ValueError(f"world config: fold is a cloth task, not allowed for {name}")
        for name, p in self.presets.items():
            _vec(p.frames, 2, f"presets.{name}.frames")
            if p.frames[0] < 8 or p.frames[1] < p.frames[0]:
                raise ValueError(f"presets.{name}.frames must be [min, max] with 8 <= min <= max")
            if not 0.0 < p.split_ratio <= 1.0:
                raise ValueError(f"presets.{name}.split_ratio must be in (0, 1]")
        _vec(self.robot_base_xyz, 3, "robot_base_xyz")
        _vec(self.table.size, 3, "table.size")
        if self.physics.timestep <= 0 or self.fps <= 0:
            raise ValueError("world config: physics.timestep and fps must be positive")
        if not self.physics.max_element_stretch > 1.0:
            raise ValueError(f"world config: physics.max_element_stretch must be > 1, got {self.physics.max_element_stretch}")

    def preset(self, name: str) -> PresetConfig:
        if name not in self.presets:
            raise ValueError(f"unknown preset '{name}' (known: {', '.join(sorted(self.presets))})")
        return self.presets[name]

    def object(self, name: str) -> ObjectConfig:
        if name not in self.objects:
            raise ValueError(f"unknown object '{name}' (known: {', '.join(sorted(self.objects))})")
        return self.objects[name]

    def steps_per_frame(self) -> int:
        n = round(1.0 / (self.fps * self.physics.timestep))
        if abs(n * self.physics.timestep * self.fps - 1.0) > 1e-6:
            raise ValueError(
                f"physics.timestep {self.physics.timestep} does not divide the frame period 1/{self.fps} s"
            )
        return int(n)


def load_world_config(path: Union[str, Path] = "world/default") -> WorldConfig:
    """Load the world YAML, its robot YAML and its effects YAML; validate all three."""
    p = resolve_config(path)
    cfg = _from_dict(WorldConfig, _read_yaml(p), p.name)
    if cfg.robot_config is not None or cfg.effects is not None:
        raise ValueError(f"{p.name}: robot_config/effects are not YAML keys (use robot / effects_config)")
    robot_ref = cfg.robot
    if not Path(robot_ref).is_file() and (p.parent / f"{robot_ref}.yaml").is_file():
        robot_ref = str(p.parent / f"{robot_ref}.yaml")
    cfg.robot_config = load_robot_config(robot_ref)
    eff_ref = cfg.effects_config
    if not Path(eff_ref).is_file() and (p.parent / f"{eff_ref}.yaml").is_file():
        eff_ref = str(p.parent / f"{eff_ref}.yaml")
    cfg.effects = load_effects_config(eff_ref)
    cfg.validate()
    return cfg
