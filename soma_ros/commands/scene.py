"""`soma scene`: make splat scenes and send them to a running node's reset service."""

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

    m = s.add_parser("synth", help="write a generated rope scene to a .ply")
    m.add_argument("--n", type=int, default=13000, help="number of splats")
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--out", required=True, help="output .ply")
    m.set_defaults(func=run_synth)

    from .scene_align import register as register_align

    register_align(s)


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
