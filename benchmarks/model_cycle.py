"""A trained model through one whole grasp-lift-lower-release cycle, without ROS.

    python -m benchmarks.model_cycle --run runs/demo [--hold 300] [--settle-s 1.0]
    python -m benchmarks.model_cycle --run runs/demo --cycles 12     # repeated cycles (the long live run's)
    python -m benchmarks.model_cycle --run runs/demo --cycles 12 --passive-friction -1   # without the rule
    python -m benchmarks.model_cycle --run runs/demo --cycles 12 --exempt-trained none     # the rule on every step
    python -m benchmarks.model_cycle --run runs/demo --cycles 12 --exempt-trained always   # exempt with the gripper open too

Steps the run's model (two steps per pose, as the live node does at 60 Hz
joint states and 120 steps/s) through ``grasp_trajectory`` forward (descend,
close, lift), backward (lower, open, rise) and then holds the last pose, and
prints the rope's centroid rise and the gripper height every 15 poses: the
figures behind the README's note on long live runs. The divergence guard is off
(``max_travel_m=0``) so the model's own behaviour shows. The passive-object rule
is on as the node runs it (``--passive-friction 0.5``; negative = off): not on steps where
the model's own terms act with the gripper closed (``--exempt-trained closed``,
``DynamicsConfig.passive_exempt`` with ``passive_exempt_closed``); ``none``: on every step (the
node's former rule); ``always``: exempt with the gripper open too.
"""

from __future__ import annotations

import argparse

import numpy as np


def _setup(run: str, settle_s: float, passive_friction: float, exempt_trained: str = "closed"):
    """(live simulator of the run with the guard off, initial splat means [N, 3], the joint
    vectors of descend-close-lift at the object's grasp point)."""
    from benchmarks.bench_live import Poser, grasp_trajectory, object_grasp
    from soma_ros.live import load_live

    if exempt_trained not in ("none", "closed", "always"):
        raise ValueError(f"exempt_trained: none, closed or always, got {exempt_trained!r}")
    live = load_live(f"{run}/checkpoint.pt", f"{run}/scene", max_travel_m=0.0, settle_s=settle_s,
                     passive_friction=passive_friction, passive_exempt_grasped=exempt_trained != "none")
    if exempt_trained == "always":
        live.sim.set_passive_friction(None, exempt_closed=False)
    poser = Poser(live.robot, live.base_to_sim.matrix(), live.required_joints,
                  np.asarray(live.bundle.gravity, dtype=np.float64))
    x0 = live.snapshot()[0].means.double().numpy()
    grasp, closing = object_grasp(x0, poser.down)
    return live, x0, grasp_trajectory(poser, grasp, lift=0.10, above=0.10, steps=30, closing=closing)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default="runs/demo", help="run folder with checkpoint.pt and scene/")
    ap.add_argument("--hold", type=int, default=300, help="steps to hold the final pose")
    ap.add_argument("--settle-s", type=float, default=0.0,
                    help="LiveSimulator settling after this long quiet with the robot out of reach (0 = off)")
    ap.add_argument("--cycles", type=int, default=0,
                    help="instead: N whole grasp-lift-lower-open cycles back to back, as the long live run "
                         "drives the node; prints the object's drift after each (settling at 2 s, as the node)")
    ap.add_argument("--passive-friction", type=float, default=0.5,
                    help="the node's passive-object rule with this friction (negative = off; default 0.5, the node's)")
    ap.add_argument("--exempt-trained", default="closed", choices=["none", "closed", "always"],
                    help="steps where the model's own terms (its robot coupling) act are not passive: only with the "
                         "gripper closed (the node's default), never (the rule on every step) or always")
    args = ap.parse_args(argv)
    if args.cycles:
        return repeated(args.run, args.cycles, args.passive_friction, args.exempt_trained)

    live, x0, cycle = _setup(args.run, args.settle_s, args.passive_friction, args.exempt_trained)

    def show(tag: str, v) -> None:
        x = live.snapshot()[0].means.double().numpy()
        act = live.action(v)
        print(f"{tag:>10}  rope centroid rise {x.mean(0)[2] - x0.mean(0)[2]:+.3f} m   "
              f"gripper z {float(act.control_points[:, 2].double().mean()):.3f} m   opening {float(act.gripper):.2f}"
              f"   settles {live.settles}")

    print(f"{args.run}: {len(x0)} splats, {len(cycle)} poses each way, 2 steps per pose, passive-object rule: "
          f"{live.sim.config.dynamics.passive_rule_text()}")
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


def repeated(run: str, n: int, passive_friction: float = 0.5, exempt_trained: str = "closed") -> int:
    """Cycles back to back (2 steps per pose); per cycle the centroid's drift from where it
    started, its height change and the farthest splat from the initial centre."""
    live, x0, fwd = _setup(run, 2.0, passive_friction, exempt_trained)
    cycle = fwd + fwd[::-1]
    c0 = x0.mean(0)
    print(f"{run}: {len(x0)} splats, {n} cycles of {len(cycle)} poses, 2 steps per pose, passive-object rule: "
          f"{live.sim.config.dynamics.passive_rule_text()}")
    for c in range(n):
        far = 0.0
        for v in cycle:
            live.step(v)
            st, _ = live.step(v)
            far = max(far, float(np.linalg.norm(st.means.double().numpy() - c0, axis=1).max()))
        x = st.means.double().numpy()
        print(f"cycle {c + 1:3d}: centroid drift {np.linalg.norm(x.mean(0) - c0):7.3f} m (height {x.mean(0)[2] - c0[2]:+.3f} m)"
              f"   farthest splat from the initial centre {far:7.3f} m   settles {live.settles}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
