"""The physics prior's constraint solvers: how stiff each makes a stiff rope, and what a step costs.

``soma_ros/core/physics.py`` solves the prior's stretch, bending and grip constraints every
substep either by over-relaxed Jacobi passes (``solver: jacobi``, ``iterations`` per substep) or
by Gauss-Newton steps on the whole node system (``solver: newton``, one dense 3K x 3K Cholesky
solve per step). Two measurements:

* **stiffness**: a 0.35 m rope (48 nodes, 16 substeps, the prior's default compliances) grasped
  at its middle, lifted 0.2 m in 1 s and held 0.5 s; how far its ends hang below the fingers
  (droop, mm). A stiff material should droop by what its bending compliance says; with Jacobi
  passes the droop falls as passes are added (the passes, not the compliance, set it), with
  Gauss-Newton it has converged after one step. Then the droop for bending compliances 1e-8 to
  1e-4 under each solver (does the compliance matter?).
* **time**: ``pbd_step`` alone (nodes only) and the whole simulator step of the
  ``tiny_physics`` model (rope, 1.5k and 13k splats, ``bench_core``'s sweeping actions) per
  device, per solver, median of the timed steps, each synced; ratio newton / jacobi.

``python -m benchmarks.physics_solver [--devices cpu cuda] [--splats 1500 13000] [--json F]``
(about 2 min on one CPU core). Prints the machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from typing import Optional, Sequence

import torch

from benchmarks.bench_core import _actions, _sync, machine_description, make_object, timed_steps
from soma_ros.core.effects.physics import PhysicsPrior, build_layout, grasp_nodes, pbd_step
from soma_ros.core.simulator import SceneContext, Simulator

__all__ = ["lifted_droop", "solver_variants", "step_times", "main"]

UP = torch.tensor([0.0, 0.0, 1.0])
GRAVITY = torch.tensor([0.0, 0.0, -9.81])
DT = 1.0 / 30.0


def _bar(p: PhysicsPrior.Params, device: str = "cpu", n: int = 400):
    pts = torch.zeros(n, 3)
    pts[:, 0] = torch.linspace(0.0, 0.35, n)
    pts[:, 2] = 0.006
    lay = build_layout(pts.to(device), torch.full((n,), 0.05 / n, device=device), UP.to(device),
                       torch.tensor(0.0, device=device), p)
    c = torch.tensor([0.175, 0.0, 0.006], device=device)
    cp = torch.stack([c + torch.tensor([0.0, 0.01, 0.0], device=device), c - torch.tensor([0.0, 0.01, 0.0], device=device)])
    return lay, cp


def _lift(p: PhysicsPrior.Params, device: str = "cpu", steps: int = 45, lift: float = 0.2, times: Optional[list] = None):
    """Node positions [K, 3] after the lift-and-hold (``times``: ms of every step appended)."""
    lay, cp = _bar(p, device)
    coef = {k: v.to(device) for k, v in PhysicsPrior(p).coefficients().items()}
    x, v, grasp = lay.rest.clone(), torch.zeros(lay.num_nodes, 3, device=device), None
    up = torch.tensor([0.0, 0.0, 1.0], device=device)
    with torch.no_grad():
        for t in range(steps):
            cp0 = cp + up * (lift * min(t / 30, 1.0))
            cp1 = cp + up * (lift * min((t + 1) / 30, 1.0))
            grasp = grasp or grasp_nodes(lay, x, cp0, p)
            _sync(device)
            t0 = time.perf_counter()
            x1, grasp = pbd_step(lay, x, v, GRAVITY.to(device), UP.to(device), torch.tensor(0.0, device=device), DT, p,
                                 coef, cp0, cp1, grasp)
            _sync(device)
            if times is not None:
                times.append((time.perf_counter() - t0) * 1e3)
            v, x = (x1 - x) / DT, x1
    return x


def lifted_droop(**params) -> float:
    """mm the lifted rope's ends hang below its highest node (module docstring)."""
    p = PhysicsPrior.Params(**{"num_nodes": 48, "substeps": 16, **params})
    x = _lift(p)
    ends = x[x[:, 0].argsort()[[0, -1]], 2]
    return 1e3 * float(x[:, 2].max() - ends.mean())


def solver_variants() -> list[tuple[str, dict]]:
    return [("jacobi 10", dict(solver="jacobi", iterations=10)), ("jacobi 40", dict(solver="jacobi", iterations=40)),
            ("jacobi 160", dict(solver="jacobi", iterations=160)), ("newton 1", dict(solver="newton", newton_iterations=1)),
            ("newton 3", dict(solver="newton", newton_iterations=3))]


def _with_solver(cfg, solver: dict):
    """The model config with ``solver`` merged into its physics term's params (every other field kept)."""
    cfg.effects = [dataclasses.replace(s, params={**s.params, **solver}) if s.name == "physics" else s
                   for s in cfg.effects]
    return cfg


def step_times(device: str, n: int, solver: dict, steps: int = 20, warmup: int = 3) -> dict:
    """ms per step: the prior's ``pbd_step`` alone (the lifted rope) and the ``tiny_physics``
    simulator step (rope of n splats)."""
    from trainer.config import load_train_config

    p = PhysicsPrior.Params(**{"num_nodes": 48, "substeps": 16, **solver})
    node_ms: list = []
    _lift(p, device, steps=warmup + steps, times=node_ms)
    cfg = _with_solver(load_train_config("tiny_physics").model_config(), solver)
    torch.manual_seed(0)
    sim = Simulator(cfg).to(device).eval()
    sp = make_object("rope", n)
    with torch.no_grad():
        state = sim.init_state(sp, SceneContext.table())
    state, times = timed_steps(sim, state, _actions(sp, warmup + steps), device, warmup)
    if not bool(torch.isfinite(state.positions[0]).all()):
        raise RuntimeError("physics_solver: non-finite state")
    return dict(device=str(device), n_splats=n, solver=solver, pbd_step_ms=statistics.median(node_ms[warmup:]),
                sim_step_ms=statistics.median(times), steps=len(times))


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", nargs="+", default=["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    ap.add_argument("--splats", type=int, nargs="+", default=[1500, 13000])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1, as the README)")
    ap.add_argument("--skip-stiffness", action="store_true")
    ap.add_argument("--json", dest="json_path", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    out: dict = dict(machine={d: machine_description(d) for d in args.devices}, droop=[], bend=[], times=[])
    for d in args.devices:
        print("machine:", out["machine"][d], flush=True)
    if not args.skip_stiffness:
        print("\nstiffness: a 0.35 m rope lifted 0.2 m at its middle; its ends' droop below the fingers (mm)")
        for name, kw in solver_variants():
            mm = lifted_droop(**kw)
            out["droop"].append(dict(solver=name, droop_mm=mm))
            print(f"  {name:>11}: {mm:6.1f} mm", flush=True)
        print("bending compliance (s^2/m) -> droop (mm), jacobi 10 passes | newton 1 step")
        for c in (1e-8, 1e-6, 1e-5, 1e-4):
            j = lifted_droop(solver="jacobi", bend_compliance=c)
            nw = lifted_droop(solver="newton", newton_iterations=1, bend_compliance=c)
            out["bend"].append(dict(bend_compliance=c, jacobi_mm=j, newton_mm=nw))
            print(f"  {c:7.0e}: {j:6.1f} | {nw:6.1f}", flush=True)
    print("\ntime per step (ms, median): prior alone (48 nodes) | tiny_physics simulator step")
    for d in args.devices:
        for n in args.splats:
            rows = {}
            for name, kw in (("jacobi 10", dict(solver="jacobi")), ("newton 1", dict(solver="newton", newton_iterations=1))):
                r = step_times(d, n, kw, args.steps)
                rows[name] = r
                out["times"].append(dict(r, name=name))
                print(f"  {d:>5} {n:6d} splats {name:>10}: {r['pbd_step_ms']:7.2f} | {r['sim_step_ms']:7.2f}", flush=True)
            a, b = rows["jacobi 10"], rows["newton 1"]
            print(f"  {d:>5} {n:6d} splats newton / jacobi: {b['pbd_step_ms'] / a['pbd_step_ms']:.2f}x | "
                  f"{b['sim_step_ms'] / a['sim_step_ms']:.2f}x", flush=True)
    if args.json_path:
        with open(args.json_path, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
