"""`soma robot check`: inspect a robot URDF for robot conditioning.

Parses the URDF (our validator, then pytorch_kinematics), prints the chain
base -> ee with joint types and limits, the end-effector pose at zero and at
random configurations, the gripper model and the control points. Unusable
URDFs or names end with a one-line error and exit code 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path
from typing import Optional

__all__ = ["register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("robot", help="inspect a robot URDF: chain, limits, end-effector and control points")
    sub = p.add_subparsers(dest="robot_command", metavar="ACTION")
    c = sub.add_parser(
        "check",
        help="parse a URDF and print chain, limits, ee poses and control points",
        description="Parse a URDF and print the chain base -> ee, joint limits, ee poses and control points.",
    )
    c.add_argument("--urdf", type=Path, help="URDF file (overrides the config's urdf)")
    c.add_argument("--ee-link", help="end-effector link (overrides the config's ee_link)")
    c.add_argument("--base-link", help="base link (default: the config's, else the URDF root)")
    c.add_argument("--gripper-joints", nargs="+", metavar="J", help="gripper joints (overrides the config's)")
    c.add_argument("--config", help="robot YAML, e.g. config/robots/panda.yaml or just 'panda'")
    c.add_argument("--samples", type=int, default=3, help="random configurations to print (default 3)")
    c.add_argument("--seed", type=int, default=0, help="seed of the random configurations")
    c.set_defaults(func=run)
    p.set_defaults(func=_robot_help(p))


def _robot_help(parser: argparse.ArgumentParser):
    def show(args: argparse.Namespace) -> int:
        parser.print_help()
        return 2

    return show


def _build_config(args: argparse.Namespace):
    from soma_ros.core.robot_config import GripperConfig, RobotConfig, load_robot_config

    if args.config:
        cfg = load_robot_config(args.config)
        changes: dict = {}
        if args.urdf is not None:
            changes["urdf"] = _existing(args.urdf)
        if args.ee_link and args.ee_link != cfg.ee_link:
            changes["ee_link"] = args.ee_link
            changes["arm_joints"] = None  # the config's arm joints belong to its own chain
        if args.base_link and args.base_link != cfg.base_link:
            changes["base_link"] = args.base_link
            changes["arm_joints"] = None
        if args.gripper_joints is not None:
            changes["gripper"] = GripperConfig(joints=tuple(args.gripper_joints))
        return dataclasses.replace(cfg, **changes) if changes else cfg
    if args.urdf is None or not args.ee_link:
        raise ValueError("give --urdf FILE and --ee-link LINK, or --config")
    gripper = GripperConfig(joints=tuple(args.gripper_joints)) if args.gripper_joints else None
    return RobotConfig(
        urdf=_existing(args.urdf), ee_link=args.ee_link, name=args.urdf.stem, base_link=args.base_link, gripper=gripper
    )


def _existing(p: Path) -> Path:
    if not p.is_file():
        raise FileNotFoundError(f"URDF file not found: {p}")
    return p.resolve()


def _fmt_limit(v: Optional[float]) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:+.4f}"


def _f(v: float, digits: int = 4) -> str:
    """Signed fixed-point without a '-0.0000' for tiny negatives."""
    r = round(float(v), digits) + 0.0
    return f"{r:+.{digits}f}"


def _vec(v, digits: int = 4) -> str:
    return "[" + " ".join(_f(x, digits) for x in v) + "]"


def _fmt_pose(T) -> str:
    import torch

    from soma_ros.core.geometry import rotmat_to_quat

    q = rotmat_to_quat(T[:3, :3].to(torch.float64))
    p = T[:3, 3]
    return f"xyz {_vec(p.tolist())} m  quat wxyz {_vec(q.tolist())}"


def run(args: argparse.Namespace) -> int:
    if getattr(args, "robot_command", None) != "check":
        raise ValueError("unknown robot action (use: soma robot check ...)")
    if args.samples < 0:
        raise ValueError(f"--samples must be >= 0, got {args.samples}")
    import torch

    torch.set_num_threads(1)
    from soma_ros.core.robot import RobotModel

    cfg = _build_config(args)
    model = RobotModel(cfg, dtype=torch.float64)
    u = model.urdf
    n_mov = sum(1 for j in u.joints.values() if j.movable)
    n_mim = sum(1 for j in u.joints.values() if j.mimic is not None)
    print(f"URDF {cfg.urdf}")
    print(f"  robot '{u.robot_name}': {len(u.links)} links, {len(u.joints)} joints ({n_mov} movable, {n_mim} mimic), root '{u.root}'")

    print(f"chain {model.base_link} -> {model.ee_link}:")
    print(f"  {model.base_link}")
    for j in model.chain_joints:
        extra = ""
        if j.movable:
            extra = f" axis {_vec(j.axis, 3)}"
            if j.mimic is not None:
                extra += f" mimic {j.mimic.multiplier:g}*{j.mimic.leader}{j.mimic.offset:+g}"
        print(f"    --[{j.name}: {j.type}{extra}]--> {j.child}")

    lo, hi = model.joint_limits()
    print(f"joint vector q ({model.n_joints}):")
    for i, name in enumerate(model.joint_names):
        jt = u.joints[name]
        role = "gripper" if name in model.gripper_joint_names else "arm"
        print(f"  {i:2d} {name:<28s} {jt.type:<10s} {role:<7s} [{_fmt_limit(float(lo[i]))}, {_fmt_limit(float(hi[i]))}]")
    mimics = [j for j in u.joints.values() if j.mimic is not None]
    for j in mimics:
        leader, mult, off = u.mimic_root(j.name)
        print(f"  mimic: {j.name} = {mult:g} * {leader} {off:+g}")

    if model.gripper_joint_names:
        ext = [j for j in model.gripper_joint_names if j not in model.joint_names]
        lo_o, hi_o = model.opening_range
        print(
            f"gripper: joints {', '.join(model.gripper_joint_names)}"
            + (f" (not in the URDF: {', '.join(ext)})" if ext else "")
            + f"; opening range [{lo_o:.4f}, {hi_o:.4f}] m (c = 0 closed, 1 open)"
        )
    else:
        print("gripper: none configured (control points at zero opening)")

    z = torch.zeros(1, model.n_joints, dtype=torch.float64)
    print(f"ee pose ({model.ee_link} in {model.base_link}):")
    print(f"  q = 0        {_fmt_pose(model.ee_pose(z)[0])}")
    if args.samples:
        g = torch.Generator().manual_seed(args.seed)
        qs = model.sample_q(args.samples, g)
        T = model.ee_pose(qs)
        for i in range(args.samples):
            print(f"  random #{i:<3d} {_fmt_pose(T[i])}")
            print(f"    q = {_vec(qs[i].tolist(), 3)}")

    cp = cfg.control_points
    print(
        f"control points: {model.n_control_points} (2 jaws x {cp.grid[0]} x {cp.grid[1]}), "
        f"jaw {cp.jaw_length:.4f} x {cp.jaw_width:.4f} m, tip offset {cp.tip_offset:.4f} m"
    )
    lo_o, hi_o = model.opening_range
    openings = (("closed", lo_o), ("open", hi_o)) if model.gripper_joint_names else (("no gripper", 0.0),)
    for label, o in openings:
        pts = model.control_points_ee(torch.tensor([o], dtype=torch.float64))[0]
        mn, mx = pts.min(0).values, pts.max(0).values
        print(
            f"  bbox in ee frame, {label} ({o:.4f} m): "
            f"min {_vec(mn.tolist())} max {_vec(mx.tolist())}"
        )
    print("OK")
    return 0
