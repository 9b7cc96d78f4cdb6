"""URDF parsing and validation for robot conditioning (pure Python, no ROS).

We read the URDF XML ourselves for three reasons:

* clear one-line errors naming the offending element (malformed XML, unknown
  link names, bad numbers, unsupported joint types, broken mimic references);
* ``<mimic>`` joints, which pytorch_kinematics ignores: we parse their
  multiplier / offset here and fill them in before FK;
* robustness: pytorch_kinematics' bundled parser chokes on some real URDFs
  (meshes, materials, vendor tags) and prints warnings for unknown tags, and it
  defaults a missing ``<axis>`` to +z where the URDF spec says +x. We hand it a
  *kinematics-only* URDF (:meth:`UrdfModel.kinematic_xml`) with every link,
  joint origin, explicit axis and limit, and nothing else.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union
from .errors import RobotError

__all__ = ["URDFError", "Mimic", "UrdfJoint", "UrdfModel", "parse_urdf", "MOVABLE_TYPES", "resolve_mesh_path"]

#: joint types whose value changes the kinematics and that FK supports
MOVABLE_TYPES = ("revolute", "continuous", "prismatic")
_KNOWN_TYPES = MOVABLE_TYPES + ("fixed", "floating", "planar")


class URDFError(RobotError):
    """A URDF that cannot be used, with a one-line message naming the element."""


@dataclass(frozen=True)
class Mimic:
    """``value(joint) = multiplier * value(leader) + offset`` (URDF <mimic>)."""

    leader: str
    multiplier: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True)
class UrdfJoint:
    """One URDF joint. ``axis`` is a unit vector in the joint frame (URDF default +x)."""

    name: str
    type: str
    parent: str
    child: str
    origin_xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    origin_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    lower: Optional[float] = None
    upper: Optional[float] = None
    mimic: Optional[Mimic] = None

    @property
    def movable(self) -> bool:
        return self.type in MOVABLE_TYPES


@dataclass
class UrdfModel:
    """The kinematic tree of a URDF: links, joints (in file order), root link."""

    source: str
    robot_name: str
    links: list[str]
    joints: dict[str, UrdfJoint]
    root: str
    #: link name -> name of the joint whose child it is (the root has none)
    parent_joint: dict[str, str] = field(default_factory=dict)

    # ------------------------------------------------------------------ queries
    def has_link(self, name: str) -> bool:
        return name in self.parent_joint or name == self.root

    def require_link(self, name: str, role: str) -> None:
        """Raise URDFError naming `name` when it is not a link of this URDF."""
        if not self.has_link(name):
            raise URDFError(
                f"{self.source}: {role} '{name}' is not a link of robot '{self.robot_name}' "
                f"(links: {', '.join(self.links)})"
            )

    def path_joints(self, base: str, tip: str) -> list[UrdfJoint]:
        """Joints from `base` down to `tip` (base first). `tip` must be `base` or below it."""
        self.require_link(base, "base link")
        self.require_link(tip, "link")
        chain: list[UrdfJoint] = []
        link = tip
        while link != base:
            jname = self.parent_joint.get(link)
            if jname is None:
                raise URDFError(
                    f"{self.source}: link '{tip}' is not below base link '{base}' in the kinematic tree"
                )
            joint = self.joints[jname]
            chain.append(joint)
            link = joint.parent
        chain.reverse()
        return chain

    def mimic_root(self, joint: str) -> tuple[str, float, float]:
        """Resolve a (possibly chained) mimic joint to (independent leader, multiplier, offset).

        For a joint that mimics nobody this is ``(joint, 1.0, 0.0)``.
        """
        mult, off = 1.0, 0.0
        name = joint
        seen = {name}
        while True:
            m = self.joints[name].mimic
            if m is None:
                return name, mult, off
            # value(name) = m.mult * value(leader) + m.off; compose with what we have so far
            off = mult * m.offset + off
            mult = mult * m.multiplier
            name = m.leader
            if name in seen:  # checked at parse time, kept as a guard
                raise URDFError(f"{self.source}: mimic cycle through joint '{name}'")
            seen.add(name)

    def mimic_followers(self, leader: str) -> list[str]:
        """Movable joints whose mimic chain ends at `leader` (not including `leader`)."""
        return [
            j.name
            for j in self.joints.values()
            if j.movable and j.mimic is not None and self.mimic_root(j.name)[0] == leader
        ]

    # ------------------------------------------------------------------ export
    def kinematic_xml(self) -> str:
        """A kinematics-only URDF string (links, joints, origins, explicit axes, limits)."""
        robot = ET.Element("robot", name=self.robot_name)
        for link in self.links:
            ET.SubElement(robot, "link", name=link)
        for j in self.joints.values():
            if not j.movable and j.type != "fixed":
                raise URDFError(
                    f"{self.source}: joint '{j.name}' has type '{j.type}', which FK does not support "
                    f"(supported: {', '.join(MOVABLE_TYPES + ('fixed',))})"
                )
            el = ET.SubElement(robot, "joint", name=j.name, type=j.type)
            ET.SubElement(
                el,
                "origin",
                xyz=" ".join(repr(v) for v in j.origin_xyz),
                rpy=" ".join(repr(v) for v in j.origin_rpy),
            )
            ET.SubElement(el, "parent", link=j.parent)
            ET.SubElement(el, "child", link=j.child)
            if j.movable:
                ET.SubElement(el, "axis", xyz=" ".join(repr(v) for v in j.axis))
            if j.lower is not None and j.upper is not None:
                ET.SubElement(el, "limit", lower=repr(j.lower), upper=repr(j.upper), effort="0", velocity="0")
        return ET.tostring(robot, encoding="unicode")


# ---------------------------------------------------------------------- parsing
def _floats(text: Optional[str], n: int, what: str, src: str, default: tuple[float, ...]) -> tuple[float, ...]:
    if text is None:
        return default
    parts = text.split()
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        raise URDFError(f"{src}: {what} must be {n} numbers, got '{text}'") from None
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise URDFError(f"{src}: {what} must be {n} finite numbers, got '{text}'")
    return vals


def _float_attr(el: ET.Element, attr: str, what: str, src: str, default: Optional[float]) -> Optional[float]:
    text = el.get(attr)
    if text is None:
        return default
    try:
        v = float(text)
    except ValueError:
        raise URDFError(f"{src}: {what} {attr}='{text}' is not a number") from None
    if math.isnan(v):
        raise URDFError(f"{src}: {what} {attr} is NaN")
    return v


def parse_urdf(source: Union[str, Path], *, text: Optional[str] = None) -> UrdfModel:
    """Parse and validate a URDF file (or `text`, with `source` used only in messages).

    Raises URDFError (a ValueError) with a one-line message naming the problem;
    FileNotFoundError when the file does not exist.
    """
    src = str(source)
    if text is None:
        path = Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"URDF file not found: {path}")
        text = path.read_text(encoding="utf-8", errors="replace")
        src = path.name
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise URDFError(f"{src}: malformed XML ({exc})") from None
    if root.tag != "robot":
        raise URDFError(f"{src}: root element is <{root.tag}>, expected <robot>")
    robot_name = root.get("name", "")

    links: list[str] = []
    for i, el in enumerate(root.findall("link")):
        name = el.get("name")
        if not name:
            raise URDFError(f"{src}: <link> number {i + 1} has no name attribute")
        if name in links:
            raise URDFError(f"{src}: link '{name}' is defined twice")
        links.append(name)
    if not links:
        raise URDFError(f"{src}: robot '{robot_name}' has no <link> elements")
    link_set = set(links)

    joints: dict[str, UrdfJoint] = {}
    parent_joint: dict[str, str] = {}
    for i, el in enumerate(root.findall("joint")):
        name = el.get("name")
        if not name:
            raise URDFError(f"{src}: <joint> number {i + 1} has no name attribute")
        what = f"joint '{name}'"
        if name in joints:
            raise URDFError(f"{src}: {what} is defined twice")
        jtype = el.get("type")
        if jtype not in _KNOWN_TYPES:
            raise URDFError(f"{src}: {what} has unknown type '{jtype}' (expected one of {', '.join(_KNOWN_TYPES)})")
        ends: dict[str, str] = {}
        for tag in ("parent", "child"):
            sub = el.find(tag)
            lname = None if sub is None else sub.get("link")
            if not lname:
                raise URDFError(f"{src}: {what} has no <{tag} link=...> element")
            if lname not in link_set:
                raise URDFError(f"{src}: {what} names {tag} link '{lname}', which is not defined")
            ends[tag] = lname
        if ends["child"] in parent_joint:
            raise URDFError(
                f"{src}: link '{ends['child']}' is the child of two joints "
                f"('{parent_joint[ends['child']]}' and '{name}')"
            )
        if ends["child"] == ends["parent"]:
            raise URDFError(f"{src}: {what} has the same parent and child link '{ends['child']}'")
        origin = el.find("origin")
        xyz = _floats(None if origin is None else origin.get("xyz"), 3, f"{what} <origin xyz>", src, (0.0, 0.0, 0.0))
        rpy = _floats(None if origin is None else origin.get("rpy"), 3, f"{what} <origin rpy>", src, (0.0, 0.0, 0.0))
        axis_el = el.find("axis")
        axis = _floats(None if axis_el is None else axis_el.get("xyz"), 3, f"{what} <axis xyz>", src, (1.0, 0.0, 0.0))
        lower = upper = None
        if jtype in MOVABLE_TYPES:
            norm = math.sqrt(sum(a * a for a in axis))
            if norm < 1e-12:
                raise URDFError(f"{src}: {what} has a zero-length <axis>")
            axis = tuple(a / norm for a in axis)
        limit = el.find("limit")
        if jtype in ("revolute", "prismatic"):
            if limit is None:
                raise URDFError(f"{src}: {what} ({jtype}) has no <limit> element (required by the URDF spec)")
            # URDF spec: lower/upper default to 0
            lower = _float_attr(limit, "lower", f"{what} <limit>", src, 0.0)
            upper = _float_attr(limit, "upper", f"{what} <limit>", src, 0.0)
            assert lower is not None and upper is not None
            if lower > upper:
                raise URDFError(f"{src}: {what} has lower limit {lower} > upper limit {upper}")
        mimic = None
        mim = el.find("mimic")
        if mim is not None and jtype in MOVABLE_TYPES:
            leader = mim.get("joint")
            if not leader:
                raise URDFError(f"{src}: {what} has a <mimic> without a joint attribute")
            mult = _float_attr(mim, "multiplier", f"{what} <mimic>", src, 1.0)
            off = _float_attr(mim, "offset", f"{what} <mimic>", src, 0.0)
            assert mult is not None and off is not None
            mimic = Mimic(leader, mult, off)
        joints[name] = UrdfJoint(
            name=name,
            type=jtype,
            parent=ends["parent"],
            child=ends["child"],
            origin_xyz=xyz,  # type: ignore[arg-type]
            origin_rpy=rpy,  # type: ignore[arg-type]
            axis=axis,  # type: ignore[arg-type]
            lower=lower,
            upper=upper,
            mimic=mimic,
        )
        parent_joint[ends["child"]] = name

    roots = [l for l in links if l not in parent_joint]
    if len(roots) != 1:
        raise URDFError(
            f"{src}: the links must form one tree, found {len(roots)} root links ({', '.join(roots) or 'none'})"
        )
    model = UrdfModel(src, robot_name, links, joints, roots[0], parent_joint)

    # every link must hang below the root (catches cycles, which leave links unreachable)
    for link in links:
        seen = {link}
        cur = link
        while cur != model.root:
            cur = joints[parent_joint[cur]].parent
            if cur in seen:
                raise URDFError(f"{src}: the joints form a cycle through link '{cur}'")
            seen.add(cur)

    for j in joints.values():
        if j.mimic is None:
            continue
        leader = joints.get(j.mimic.leader)
        if leader is None:
            raise URDFError(f"{src}: joint '{j.name}' mimics joint '{j.mimic.leader}', which is not defined")
        if not leader.movable:
            raise URDFError(f"{src}: joint '{j.name}' mimics joint '{leader.name}', which is {leader.type}")
        seen = {j.name}
        cur = j
        while cur.mimic is not None:
            if cur.mimic.leader in seen:
                raise URDFError(f"{src}: mimic cycle through joint '{cur.mimic.leader}'")
            seen.add(cur.mimic.leader)
            cur = joints[cur.mimic.leader]
    return model


def resolve_mesh_path(filename: str, urdf_dir: Path) -> Path:
    """A URDF mesh reference (``package://pkg/rel``, ``file://``, relative) as an existing file."""
    cands: list[Path] = []
    if filename.startswith("package://"):
        rest = filename[len("package://") :]
        parts = Path(rest).parts
        # package://<pkg>/<rel>: <pkg> is the URDF's folder (or an ancestor), or a folder beside it.
        cands.append(urdf_dir / rest)
        if len(parts) > 1:
            rel = Path(*parts[1:])
            cands.append(urdf_dir / rel)
            for anc in [urdf_dir, *urdf_dir.parents]:
                if anc.name == parts[0]:
                    cands.append(anc / rel)
                cands.append(anc / parts[0] / rel)
    elif filename.startswith("file://"):
        cands.append(Path(filename[len("file://") :]))
    else:
        p = Path(filename)
        cands += [p if p.is_absolute() else urdf_dir / p]
    for c in cands:
        if c.is_file():
            return c.resolve()
    raise FileNotFoundError(f"URDF mesh not found: {filename} (relative to {urdf_dir})")
