"""`soma scene`: inspect, convert and export splat scenes, and send them to a running node's reset service.

``info`` describes a .ply / .splat file or a scene bundle folder (count, SH degree,
properties, bounds); ``convert`` rewrites a file as .ply (graphdeco layout, SH degree
0-3) or .splat; ``export`` writes a scene bundle's (or a run's) splats as a standard
3DGS file that other tools (graphdeco's loader, the SIBR viewer, web viewers) read.
"""

from __future__ import annotations

import argparse
import os
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scene", help="make splat scenes and reset a running simulator node",
                       description="Make splat scenes and send them to a running soma_sim_node.")
    s = p.add_subparsers(dest="scene_cmd", metavar="ACTION", required=True)

    r = s.add_parser("reset", help="call <prefix>/reset (soma_msgs/srv/ResetScene) on a running node",
                     description="Call the ResetScene service of a running soma_sim_node with a scene "
                                 "sent as a PointCloud2 (from a file or generated), or as a path the node reads.")
    src = r.add_mutually_exclusive_group(required=True)
    src.add_argument("--file", help="local .ply/.splat: loaded here and sent as a splat PointCloud2")
    src.add_argument("--ply-path", help="path the NODE reads itself (sent in ply_path)")
    src.add_argument("--synthetic", type=int, metavar="N", help="send a generated rope of N splats")
    src.add_argument("--empty", action="store_true", help="send an empty request (the node must refuse it)")
    r.add_argument("--service", default="/soma/reset", help="service name (default /soma/reset)")
    r.add_argument("--frame", default="", help="frame_id of the sent cloud (default: the node's sim frame)")
    r.add_argument("--timeout", type=float, default=20.0, help="seconds to wait for the service and the answer")
    r.set_defaults(func=run_reset)

    i = s.add_parser("info", help="describe a .ply / .splat file or a scene bundle folder",
                     description="Count, SH degree, stored properties, bounds and splat sizes of a scene file.")
    i.add_argument("path", help=".ply, .splat, a scene bundle folder (splats.ply) or a run folder (scene/)")
    i.set_defaults(func=run_info)

    c = s.add_parser("convert", help="rewrite a scene file as .ply or .splat (by the output's extension)",
                     description="Read a .ply / .splat and write it as .ply (binary little endian, graphdeco "
                                 "layout) or .splat (32 bytes a splat, SH degree 0).")
    c.add_argument("input", help="input .ply / .splat")
    c.add_argument("output", help="output .ply / .splat")
    _ply_options(c)
    c.set_defaults(func=run_convert)

    e = s.add_parser("export", help="write a scene bundle's splats as a standard 3DGS .ply / .splat",
                     description="Write the initial splats of a scene bundle (or of a run's scene/) as a file in the "
                                 "standard layout: the graphdeco .ply without soma extras (what the SIBR viewer "
                                 "reads) or the .splat web-viewer layout.")
    e.add_argument("scene", help="scene bundle folder, or a run folder holding scene/")
    e.add_argument("output", help="output .ply / .splat")
    _ply_options(e)
    e.set_defaults(func=run_export)

    m = s.add_parser("synth", help="write a generated rope scene to a .ply")
    m.add_argument("--n", type=int, default=13000, help="number of splats")
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--out", required=True, help="output .ply")
    m.set_defaults(func=run_synth)

    from .scene_align import register as register_align

    register_align(s)


def _ply_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sh-degree", type=int, choices=[0, 1, 2, 3], default=None,
                   help="SH degree of a written .ply: higher bands zero-padded or cut (default: the input's)")
    p.add_argument("--extras", action="store_true",
                   help="also write soma's mass and attr_* properties into a .ply (plyfile-based loaders ignore "
                        "them; the SIBR viewer's fixed-record reader does not accept them)")


def _scene_file(path: str):
    from pathlib import Path

    p = Path(path)
    if p.is_dir():
        for cand in (p / "splats.ply", p / "scene" / "splats.ply"):
            if cand.is_file():
                return cand
        raise FileNotFoundError(f"{p}: neither a scene bundle (splats.ply) nor a run folder (scene/splats.ply)")
    if not p.is_file():
        raise FileNotFoundError(f"scene file not found: {p}")
    return p


def _write(splats, out: str, sh_degree, extras: bool) -> str:
    from pathlib import Path

    from ..core.ply import write_ply, write_splat

    ext = Path(out).suffix.lower()
    if ext == ".ply":
        write_ply(out, splats, extras=extras, sh_degree=sh_degree)
        k = splats.sh_rest.shape[1] if sh_degree is None else (sh_degree + 1) ** 2 - 1
        return f"binary little-endian .ply, SH degree {int(round((k + 1) ** 0.5)) - 1}" + (", with extras" if extras else "")
    if ext == ".splat":
        if sh_degree not in (None, 0) or extras:
            raise ValueError(".splat stores SH degree 0 and no extras: drop --sh-degree / --extras")
        write_splat(out, splats)
        return ".splat (SH degree 0, 8-bit colour and rotation)"
    raise ValueError(f"{out}: output must end in .ply or .splat")


def run_info(args: argparse.Namespace) -> int:
    from ..core.ply import load_splats, read_ply_header, sh_degree_of

    p = _scene_file(args.path)
    s = load_splats(p)
    print(f"{p}: {len(s)} splats")
    if p.suffix.lower() == ".ply":
        h = read_ply_header(p)
        props = list(h.property_types())
        print(f"  format {h.format}, {len(props)} vertex properties: {' '.join(props)}")
        print(f"  elements: {', '.join(f'{n} {c}' for n, c, _ in h.elements)}")
    else:
        print("  format .splat (32 bytes a splat)")
    print(f"  SH degree {sh_degree_of(s.sh_rest.shape[1])}, {s.attrs.shape[1]} learned attributes, "
          f"total mass {float(s.mass.sum()):.4g} kg")
    if len(s):
        m = s.means.double()
        lo, hi = m.min(0).values.tolist(), m.max(0).values.tolist()
        sc = s.scales.double().max(-1).values
        print("  bounds x {:.4g}..{:.4g}  y {:.4g}..{:.4g}  z {:.4g}..{:.4g} m".format(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]))
        print(f"  largest std dev per splat: median {float(sc.median()):.3g} m, max {float(sc.max()):.3g} m; "
              f"opacity median {float(s.opacities.double().median()):.3g}")
    return 0


def run_convert(args: argparse.Namespace) -> int:
    from ..core.ply import load_splats

    s = load_splats(_scene_file(args.input))
    what = _write(s, args.output, args.sh_degree, args.extras)
    print(f"wrote {len(s)} splats to {args.output}: {what}")
    return 0


def run_export(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..core.ply import load_splats

    if not Path(args.scene).is_dir():
        raise FileNotFoundError(f"{args.scene}: not a folder (a scene bundle or a run folder is expected)")
    s = load_splats(_scene_file(args.scene))
    what = _write(s, args.output, args.sh_degree, args.extras)
    print(f"wrote {len(s)} splats to {args.output}: {what}")
    return 0


def run_synth(args: argparse.Namespace) -> int:
    from ..core.ply import write_ply
    from ..core.scenes import synthetic_rope

    s = synthetic_rope(args.n, seed=args.seed)
    write_ply(args.out, s)
    print(f"wrote {len(s)} splats to {args.out}")
    return 0


def run_reset(args: argparse.Namespace) -> int:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from soma_msgs.srv import ResetScene

    from ..nodes.conversions import splats_to_cloud

    req = ResetScene.Request()
    if args.file:
        from ..core.ply import load_splats

        req.splats = splats_to_cloud(load_splats(args.file), args.frame)
    elif args.synthetic is not None:
        from ..core.scenes import synthetic_rope

        req.splats = splats_to_cloud(synthetic_rope(args.synthetic), args.frame)
    elif args.ply_path:
        req.ply_path = os.path.abspath(args.ply_path)

    rclpy.init()
    try:
        node = rclpy.create_node("soma_scene_reset_client")
        client = node.create_client(ResetScene, args.service)
        if not client.wait_for_service(timeout_sec=args.timeout):
            raise RuntimeError(f"service {args.service} not available after {args.timeout:.0f} s")
        future = client.call_async(req)
        rclpy.spin_until_future_complete(node, future, timeout_sec=args.timeout)
        if not future.done():
            raise RuntimeError(f"no answer from {args.service} within {args.timeout:.0f} s")
        resp = future.result()
        print(f"success={resp.success} num_splats={resp.num_splats} sent={req.splats.width * req.splats.height} "
              f"message={resp.message!r}")
        return 0 if resp.success else 1
    finally:
        rclpy.shutdown()
