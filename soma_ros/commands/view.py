"""`soma view`: a live 3D view of the twin in the browser (splats, robot, cameras, table).

    soma view --run RUN            the model stepped here, teleoperated from the browser
    soma view --node               follow a running soma_sim_node over ROS topics
    soma view --resim OUT          play a `soma resim` output back with a time slider

Open the printed address (default http://127.0.0.1:8080) in a browser. The page is
served from the viser package itself: no network access is needed. See docs/viewer.md.
"""

from __future__ import annotations

import argparse
import time

def register(sub) -> None:
    p = sub.add_parser("view", help="a live 3D view of the twin in the browser (splats, robot, cameras)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = p.add_mutually_exclusive_group(required=True)
    mode.add_argument("--run", metavar="RUN", help="a `soma train` run directory (or its checkpoint.pt): step it here")
    mode.add_argument("--node", action="store_true", help="follow a running soma_sim_node over ROS topics")
    mode.add_argument("--resim", metavar="OUT", help="a `soma resim` output directory (its resim_bag/)")
    p.add_argument("--scene", help="--run: scene bundle directory (default: RUN/scene); --resim: the run's scene (for the table)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default: 127.0.0.1, this machine only)")
    p.add_argument("--port", type=int, default=8080, help="port to serve on (0: any free port)")
    p.add_argument("--layers", default="splats,robot,cameras,table",
                   help="layers to draw, comma-separated (splats, robot, cameras, table)")
    p.add_argument("--rate", type=float, default=30.0, help="--run: physics step rate, Hz")
    p.add_argument("--draw-rate", type=float, default=10.0, help="how often the view is redrawn, Hz")
    p.add_argument("--image-rate", type=float, default=5.0, help="how often camera images are redrawn, Hz (0: --run draws them once, --node never)")
    p.add_argument("--device", default="cpu", help="--run: torch device")
    p.add_argument("--prefix", default="/soma", help="--node: the node's topic_prefix")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: until Ctrl-C)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..viewer.scene import TwinView

    layers = [x.strip() for x in args.layers.split(",") if x.strip()]
    for name, v in (("--rate", args.rate), ("--draw-rate", args.draw_rate)):
        if not v > 0:
            raise ValueError(f"{name} must be > 0, got {v}")
    if args.image_rate < 0:
        raise ValueError(f"--image-rate must be >= 0, got {args.image_rate}")
    if args.run:  # check the inputs before a server is started
        from ..viewer.run import resolve_run

        resolve_run(args.run, args.scene)
    elif args.resim:
        from ..viewer.resim import find_resim_bag

        find_resim_bag(args.resim)
    view = TwinView(args.host, args.port, layers=layers)
    source = None
    try:
        if args.run:
            from ..viewer.run import RunSource

            source = RunSource(view, args.run, args.scene, rate_hz=args.rate, draw_hz=args.draw_rate,
                               image_hz=args.image_rate, device=args.device)
        elif args.node:
            from ..viewer.node import NodeSource

            source = NodeSource(view, prefix=args.prefix, draw_hz=args.draw_rate, image_hz=args.image_rate)
        else:
            from ..viewer.resim import ResimSource

            source = ResimSource(view, args.resim, scene=args.scene)
        source.start()
        print(f"soma view: serving {view.url} (Ctrl-C to stop)", flush=True)
        t_end = time.monotonic() + args.duration if args.duration > 0 else None
        while t_end is None or time.monotonic() < t_end:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        if source is not None:
            source.stop()
        view.close()
    return 0
