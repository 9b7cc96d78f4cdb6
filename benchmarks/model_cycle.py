"""A trained model through one whole grasp-lift-lower-release cycle, without ROS.

    python -m benchmarks.model_cycle --run runs/demo [--hold 300] [--settle-s 1.0]

Steps the run's model (two steps per pose, as the live node does at 60 Hz
joint states and 120 steps/s) through ``grasp_trajectory`` forward (descend,
close, lift), backward (lower, open, rise) and then holds the last pose, and
prints the rope's centroid rise and the gripper height every 15 poses: the
figures behind the README's note on long live runs. The divergence guard is off
(``max_travel_m=0``) so the model's own behaviour shows.
"""

from __future__ import annotations

import argparse

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default="runs/demo", help="run folder with checkpoint.pt and scene/")
    ap.add_argument("--hold", type=int, default=300, help="steps to hold the final pose")
    ap.add_argument("--settle-s", type=float, default=0.0,
                    help="LiveSimulator settling after this long quiet with the robot out of reach (0 = off)")
    args = ap.parse_args(argv)

    from benchmarks.bench_live import Poser, grasp_trajectory, object_grasp
    from soma_ros.live import load_live

    live = load_live(f"{args.run}/checkpoint.pt", f"{args.run}/scene", max_travel_m=0.0, settle_s=args.settle_s)
    poser = Poser(live.robot, live.base_to_sim.matrix(), live.required_joints,
                  np.asarray(live.bundle.gravity, dtype=np.float64))
    x0 = live.snapshot()[0].means.double().numpy()
    grasp, closing = object_grasp(x0, poser.down)
    cycle = grasp_trajectory(poser, grasp, lift=0.10, above=0.10, steps=30, closing=closing)

    def show(tag: str, v) -> None:
        x = live.snapshot()[0].means.double().numpy()
        act = live.action(v)
        print(f"{tag:>10}  rope centroid rise {x.mean(0)[2] - x0.mean(0)[2]:+.3f} m   "
              f"gripper z {float(act.control_points[:, 2].double().mean()):.3f} m   opening {float(act.gripper):.2f}"
              f"   settles {live.settles}")

    print(f"{args.run}: {len(x0)} splats, {len(cycle)} poses each way, 2 steps per pose")
    for name, path in (("grasp+lift", cycle), ("lower+open", cycle[::-1])):
        for i, v in enumerate(path):
            live.step(v)
            live.step(v)
            if i % 15 == 14:
                show(f"{name} {i + 1}", v)
    for k in range(args.hold):
        live.step(cycle[0])
        if k % 60 == 59:
            show(f"hold {k + 1}", cycle[0])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
