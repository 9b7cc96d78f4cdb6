"""Robot configuration for robot conditioning: dataclasses loaded from YAML.

A robot YAML (see ``config/robots/panda.yaml``) names the URDF, the base and
end-effector links, the ordered arm joints, the gripper (which joint values
arrive in ``/joint_states`` and how they turn into an opening in metres and a
normalised state c_t in [0, 1]) and the control-point geometry.

Relative ``urdf`` paths resolve against the YAML's folder first, then against
:data:`soma_ros.paths.ROBOTS_DIR`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping, Optional, Union

from .config import ConfigError, read_config

from soma_ros.paths import ROBOTS_DIR, resolve_config
from .errors import RobotError

__all__ = [
    "RobotConfigError",
    "OpeningModel",
    "GripperConfig",
    "ControlPointConfig",
    "RobotConfig",
    "load_robot_config",
    "resolve_urdf_path",
]


class RobotConfigError(RobotError):
    """A robot config that cannot be used (one-line message naming the key)."""


@dataclass(frozen=True)
class OpeningModel:
    """Linear model of the gripper opening (distance between the jaws, metres).

    ``opening = offset + sum_j coeffs[j] * value(j)`` where ``value(j)`` is a
    gripper joint value from the joint state, or a URDF mimic joint computed
    from its leader. ``range = (closed, fully open)`` maps the opening to the
    normalised gripper state ``c = (opening - closed) / (open - closed)``,
    clipped to [0, 1]: c = 0 closed, c = 1 fully open.

    ``coeffs=None`` means 1.0 for every gripper joint and each of its URDF
    mimic followers (Panda: finger1 + finger2). ``range=None`` means the
    opening at the gripper joints' lower and upper limits.
    """

    coeffs: Optional[dict[str, float]] = None
    offset: float = 0.0
    range: Optional[tuple[float, float]] = None


@dataclass(frozen=True)
class GripperConfig:
    """Which joint-state values describe the gripper.

    ``joints``: independent gripper values read from the joint state, in order.
    A joint that is in the URDF becomes part of the FK joint vector (its URDF
    mimic followers are filled in). A joint that is not in the URDF (ARX X5:
    the gripper opening arrives as one more named value) must be listed in
    ``external_joints`` with its (lower, upper) range; it only feeds the
    opening model.
    """

    joints: tuple[str, ...] = ()
    external_joints: dict[str, tuple[float, float]] = field(default_factory=dict)
    opening: OpeningModel = field(default_factory=OpeningModel)


@dataclass(frozen=True)
class ControlPointConfig:
    """Gripper control points: two jaws, each a ``grid[0] x grid[1]`` grid, in the ee frame.

    Jaw k (k = +1 first, then k = -1) holds the points

        p = (tip_offset - u * jaw_length) * a + v * jaw_width * w + k * (opening / 2) * c

    for u in linspace(0, 1, grid[0]) and v in linspace(-1/2, 1/2, grid[1]),
    where a = approach axis (towards the fingertips), c = closing axis (jaw +1
    moves along +c when the gripper opens) and w = a x c. ``tip_offset`` is the
    distance from the ee_link origin to the jaw tips along a.
    """

    count: int = 30
    grid: tuple[int, int] = (5, 3)
    jaw_length: float = 0.02
    jaw_width: float = 0.02
    closing_axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    approach_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    tip_offset: float = 0.0

    def __post_init__(self) -> None:
        rows, cols = self.grid
        if rows < 1 or cols < 1:
            raise RobotConfigError(f"control_points.grid must be two positive integers, got {list(self.grid)}")
        if self.count != 2 * rows * cols:
            raise RobotConfigError(
                f"control_points.count={self.count} must equal 2 jaws x grid {rows}x{cols} = {2 * rows * cols}"
            )
        if self.jaw_length < 0 or self.jaw_width < 0:
            raise RobotConfigError("control_points.jaw_length and jaw_width must be >= 0")
        a = self.approach_axis
        c = self.closing_axis
        na = math.sqrt(sum(x * x for x in a))
        nc = math.sqrt(sum(x * x for x in c))
        if na < 1e-9 or nc < 1e-9:
            raise RobotConfigError("control_points.approach_axis and closing_axis must be non-zero")
        cos = abs(sum(x * y for x, y in zip(a, c))) / (na * nc)
        if cos > 1e-6:
            raise RobotConfigError(
                f"control_points.approach_axis {list(a)} and closing_axis {list(c)} must be perpendicular"
            )


@dataclass(frozen=True)
class RobotConfig:
    """Everything robot conditioning needs to know about one robot.

    ``base_link=None`` means the URDF root; ``arm_joints=None`` means the
    movable, non-mimic joints on the path base_link -> ee_link that are not
    gripper joints (URDF order). ``joint_aliases`` maps names used in the
    joint-state messages to the URDF / config names.
    """

    urdf: Path
    ee_link: str
    name: str = "robot"
    base_link: Optional[str] = None
    arm_joints: Optional[tuple[str, ...]] = None
    gripper: Optional[GripperConfig] = None
    control_points: ControlPointConfig = field(default_factory=ControlPointConfig)
    joint_aliases: dict[str, str] = field(default_factory=dict)

    # ---------------------------------------------------------------- loading
    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, base_dir: Optional[Path] = None, source: str = "config") -> "RobotConfig":
        """Build from a YAML-like mapping; unknown keys are errors naming the key."""
        if not isinstance(data, Mapping):
            raise RobotConfigError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
        _check_keys(data, cls, source, "")
        for key in ("urdf", "ee_link"):
            if not data.get(key):
                raise RobotConfigError(f"{source}: missing required key '{key}'")
        urdf = resolve_urdf_path(str(data["urdf"]), base_dir)
        gripper = None
        if data.get("gripper") is not None:
            g = data["gripper"]
            if not isinstance(g, Mapping):
                raise RobotConfigError(f"{source}: 'gripper' must be a mapping")
            _check_keys(g, GripperConfig, source, "gripper.")
            op = g.get("opening") or {}
            if not isinstance(op, Mapping):
                raise RobotConfigError(f"{source}: 'gripper.opening' must be a mapping")
            _check_keys(op, OpeningModel, source, "gripper.opening.")
            coeffs = op.get("coeffs")
            opening = OpeningModel(
                coeffs=None if coeffs is None else {str(k): _num(v, f"{source}: gripper.opening.coeffs.{k}") for k, v in coeffs.items()},
                offset=_num(op.get("offset", 0.0), f"{source}: gripper.opening.offset"),
                range=None if op.get("range") is None else _pair(op["range"], f"{source}: gripper.opening.range"),
            )
            ext = {
                str(k): _pair(v, f"{source}: gripper.external_joints.{k}")
                for k, v in (g.get("external_joints") or {}).items()
            }
            gripper = GripperConfig(joints=_names(g.get("joints") or [], f"{source}: gripper.joints"), external_joints=ext, opening=opening)
        cp_data = data.get("control_points") or {}
        if not isinstance(cp_data, Mapping):
            raise RobotConfigError(f"{source}: 'control_points' must be a mapping")
        _check_keys(cp_data, ControlPointConfig, source, "control_points.")
        defaults = ControlPointConfig()
        grid = cp_data.get("grid", defaults.grid)
        if not isinstance(grid, (list, tuple)) or len(grid) != 2 or not all(isinstance(x, int) for x in grid):
            raise RobotConfigError(f"{source}: control_points.grid must be two integers, got {grid!r}")
        count = cp_data.get("count", defaults.count)
        if not isinstance(count, int):
            raise RobotConfigError(f"{source}: control_points.count must be an integer, got {count!r}")
        cp_kwargs = dict(
            count=count,
            grid=(grid[0], grid[1]),
            jaw_length=_num(cp_data.get("jaw_length", defaults.jaw_length), f"{source}: control_points.jaw_length"),
            jaw_width=_num(cp_data.get("jaw_width", defaults.jaw_width), f"{source}: control_points.jaw_width"),
            closing_axis=_vec3(cp_data.get("closing_axis", defaults.closing_axis), f"{source}: control_points.closing_axis"),
            approach_axis=_vec3(cp_data.get("approach_axis", defaults.approach_axis), f"{source}: control_points.approach_axis"),
            tip_offset=_num(cp_data.get("tip_offset", defaults.tip_offset), f"{source}: control_points.tip_offset"),
        )
        try:
            cp = ControlPointConfig(**cp_kwargs)  # type: ignore[arg-type]
        except RobotConfigError as exc:
            raise RobotConfigError(f"{source}: {exc}") from None
        aliases = data.get("joint_aliases") or {}
        if not isinstance(aliases, Mapping):
            raise RobotConfigError(f"{source}: 'joint_aliases' must be a mapping of message name -> joint name")
        arm = data.get("arm_joints")
        return cls(
            urdf=urdf,
            ee_link=str(data["ee_link"]),
            name=str(data.get("name", "robot")),
            base_link=None if data.get("base_link") is None else str(data["base_link"]),
            arm_joints=None if arm is None else _names(arm, f"{source}: arm_joints"),
            gripper=gripper,
            control_points=cp,
            joint_aliases={str(k): str(v) for k, v in aliases.items()},
        )

    @classmethod
    def from_yaml(cls, path: Union[str, Path]) -> "RobotConfig":
        """Load a robot YAML file."""
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"robot config not found: {p}")
        try:
            data = read_config(p)
        except ConfigError as exc:
            raise RobotConfigError(str(exc)) from None
        return cls.from_dict(data, base_dir=p.resolve().parent, source=p.name)


def resolve_urdf_path(urdf: str, base_dir: Optional[Path] = None) -> Path:
    """An absolute URDF path: as given if absolute, else under `base_dir`, else under ROBOTS_DIR."""
    p = Path(urdf).expanduser()
    if p.is_absolute():
        return p
    cands = ([base_dir / p] if base_dir is not None else []) + [Path.cwd() / p, ROBOTS_DIR / p]
    for cand in cands:
        if cand.is_file():
            return cand.resolve()
    raise FileNotFoundError(f"URDF '{urdf}' not found (looked in {', '.join(str(c.parent) for c in cands)})")


def load_robot_config(name_or_path: Union[str, Path]) -> RobotConfig:
    """Load `config/robots/<name>.yaml` by robot name (``panda``), config-relative path or file path."""
    s = str(name_or_path)
    try:
        path = resolve_config(s)
    except FileNotFoundError:
        path = resolve_config(f"robots/{s}")
    return RobotConfig.from_yaml(path)


# ---------------------------------------------------------------------- helpers
def _check_keys(data: Mapping[str, Any], cls: type, source: str, prefix: str) -> None:
    allowed = {f.name for f in fields(cls)}
    for key in data:
        if key not in allowed:
            raise RobotConfigError(
                f"{source}: unknown key '{prefix}{key}' (allowed: {', '.join(sorted(allowed))})"
            )


def _num(v: Any, what: str) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise RobotConfigError(f"{what} must be a number, got {v!r}") from None
    if not math.isfinite(x):
        raise RobotConfigError(f"{what} must be finite, got {v!r}")
    return x


def _pair(v: Any, what: str) -> tuple[float, float]:
    if not isinstance(v, (list, tuple)) or len(v) != 2:
        raise RobotConfigError(f"{what} must be [lower, upper], got {v!r}")
    lo, hi = _num(v[0], what), _num(v[1], what)
    if lo >= hi:
        raise RobotConfigError(f"{what} must have lower < upper, got {list(v)}")
    return lo, hi


def _vec3(v: Any, what: str) -> tuple[float, float, float]:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise RobotConfigError(f"{what} must be 3 numbers, got {v!r}")
    return (_num(v[0], what), _num(v[1], what), _num(v[2], what))


def _names(v: Any, what: str) -> tuple[str, ...]:
    if isinstance(v, str) or not isinstance(v, (list, tuple)):
        raise RobotConfigError(f"{what} must be a list of joint names, got {v!r}")
    names = tuple(str(x) for x in v)
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise RobotConfigError(f"{what} lists {', '.join(dup)} more than once")
    return names
