"""The own-error control of the discrepancy workflow on a synthetic world, over seeds.

    python -m benchmarks.discrepancy_calibration --iters 24 --seeds 0,1,2 --noise 0.003

The world is the untrained CPU model plus a wind a0 = (0, 0.6, 0) m/s^2 that the model lacks
(its own error, on any data); the measured data have either a0 (case ``a0``: nothing new, the
workflow must name nothing) or a0 + a1, a1 = (0.6, 0, 0) (case ``a01``: a new wind). Rope in the
air, 13 steps, points observed every third splat with ``--noise`` m of Gaussian noise. Per seed
(torch init and the fit's episode order) and case it prints what
:func:`trainer.discrepancy.rank_candidates` (candidates wind, linear_drag; calibrated on
``--reference`` effect-free episodes) names, the wind's held-out explained fraction and its 5%
bound (the decision floor is 0.1), and the calibrated, continued and re-fitted wind. The same
setting as ``test/test_discrepancy.py::test_calibration_on_the_models_own_conditions_...``
(seed 0), which asserts the names; this shows the margins.
"""

from __future__ import annotations

import argparse
import copy
import os
import sys


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.discrepancy_calibration", description=__doc__.splitlines()[0])
    p.add_argument("--iters", type=int, default=24, help="Adam steps per fit")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds")
    p.add_argument("--noise", type=float, default=0.003, metavar="M", help="observation noise, m (std)")
    p.add_argument("--reference", type=int, default=2, metavar="N", help="reference episodes")
    args = p.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))
    from soma_ros.core.config import load_model_config
    from soma_ros.core.scenes import synthetic_rope
    from soma_ros.core.simulator import SceneContext, Simulator
    from trainer.discrepancy import EpisodeObs, _rollout, load_discrepancy_config, rank_candidates, residual_per_frame

    T, frames = 13, [4, 8, 12]
    a0, a01 = [0.0, 0.6, 0.0], [0.6, 0.6, 0.0]
    print(f"iters {args.iters}, noise {args.noise} m, {args.reference} reference episodes; decision floor 0.1")
    for seed in [int(s) for s in args.seeds.split(",")]:
        torch.manual_seed(seed)
        scene = SceneContext.table()
        sim = Simulator(load_model_config("cpu")).eval()

        def episodes(accel, seeds, split):
            world = copy.deepcopy(sim)
            world.add_effect({"name": "wind", "direct": True, "accel": accel})
            out = []
            for s in seeds:
                sp = synthetic_rope(300, seed=s, center=(0.0, 0.0, 0.3))
                world.init_state(sp, scene)
                ob = EpisodeObs(f"e{s}", None, split, scene.dt, torch.full((T, 4, 3), 3.0), torch.ones(T), sp, frames, [])
                g = torch.Generator().manual_seed(1000 + s)
                with torch.no_grad():
                    ob.points = [st.means[::3] + args.noise * torch.randn(st.means[::3].shape, generator=g)
                                 for _, st in _rollout(world, ob, scene, frames)]
                out.append(ob)
            return out

        sim.init_state(synthetic_rope(300, seed=1, center=(0.0, 0.0, 0.3)), scene)  # bind
        ref = episodes(a0, list(range(1, 1 + args.reference)), "train")
        cfg = load_discrepancy_config("fast", {"candidates": ["wind", "linear_drag"], "fit_iters": args.iters,
                                               "line_search": [0.5, 1.0, 1.5], "bootstrap": 300, "seed": seed})
        for case, accel in (("a0", a0), ("a01", a01)):
            fit, held = episodes(accel, [3, 4], "train"), episodes(accel, [5, 6], "test")
            base = [residual_per_frame(sim, o, scene) for o in held]
            named, _, _, fits, _, samples = rank_candidates(sim, fit, held, base, scene, cfg, lambda *a: None, ref)
            w = fits["wind"]
            r = lambda v: [round(x, 2) for x in v["accel"]]  # noqa: E731
            print(f"seed {seed} {case:3s}: named {named:5s} wind explained {w['explained_fraction']:+.3f} "
                  f"(bound {float(torch.tensor(samples['wind']).quantile(cfg.alpha)):+.3f}); calibrated "
                  f"{r(w['reference_parameters'])} continued {r(w['reference_continued_parameters'])} "
                  f"re-fitted {r(w['parameters'])}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
