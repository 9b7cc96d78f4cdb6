"""What the per-step finite check in ``Simulator.step`` costs, and the physics-prior model's step time.

``Simulator.step`` ends with ``if not bool(torch.isfinite(nxt.positions[0]).all()): raise
SimulationDiverged(...)``. On CUDA the ``bool()`` copies one value to the host, so the CPU waits
for every kernel queued so far: a host sync each step. This benchmark measures what that costs:

* ``finite``: one model (default ``paper``) at one splat count (default 13k, the cloth object of
  :mod:`benchmarks.bench_core`, the robot's control points sweeping through it) on one device,
  ``Simulator.step`` timed with the check as it is ("check") and with it bypassed ("bypass"),
  in alternating blocks of ``--steps`` steps from the same initial state and actions, each
  block timed two ways: ``synced`` (a device sync before and after every step, the way
  ``bench_core`` times; the check's own kernels and copy show up, the lost overlap does not)
  and ``stream`` (the steps back to back, one sync at the end; per-step time = total / steps, so
  the CPU/GPU overlap the sync prevents shows up too). The bypass replaces, for the duration
  of the bypassed blocks, the ``torch`` name in :mod:`soma_ros.core.simulator` by a copy of
  the module namespace whose ``isfinite`` returns an always-finite stand-in when (and only
  when) it is called from ``Simulator.step`` itself; nothing else in the step changes.
  Also: the check alone (``bool(torch.isfinite(x).all())`` on the step's positions with the
  device idle, median of 200), and on CUDA the number of host syncs in one step and where
  they happen (``torch.cuda.set_sync_debug_mode("warn")``).
* ``physics``: the physics-prior model (``config/train/tiny_physics.yaml``: the ``cpu`` model
  with effect ``physics``, object ``rope``) stepped like ``bench_core`` does, per device.

Usage: ``python -m benchmarks.cuda_step_check --device cuda [--model paper --splats 13000]
[--physics-devices cpu cuda] [--json out.json]``; ``benchmarks/cuda_check.sh`` runs it on a GPU
machine. Each section catches its own error and prints the traceback, so one failure does not
lose the rest; the exit status is 1 if any section failed.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import traceback
import types
import warnings
from contextlib import contextmanager
from typing import Optional, Sequence

import torch

import soma_ros.core.simulator as simulator_module
from benchmarks.bench_core import _actions, _sync, machine_description, make_object, timed_steps
from soma_ros.core.config import load_model_config
from soma_ros.core.simulator import SceneContext, Simulator

__all__ = ["bypass_finite_check", "finite_check_cost", "physics_step", "main"]


class _AlwaysFinite:
    """Stand-in for ``torch.isfinite(x)`` whose ``.all()`` is a plain True (no device work)."""

    def all(self):  # noqa: A003 - mirrors Tensor.all
        return True


@contextmanager
def bypass_finite_check():
    """Within the block ``Simulator.step``'s finite check does no work (always passes)."""
    step_code = Simulator.step.__code__
    real_isfinite = torch.isfinite
    proxy = types.ModuleType("torch_without_step_finite_check")
    proxy.__dict__.update(vars(torch))  # same objects: attribute lookups cost what they cost on torch

    def isfinite(x, *args, **kwargs):
        if sys._getframe(1).f_code is step_code:
            return _AlwaysFinite()
        return real_isfinite(x, *args, **kwargs)

    proxy.isfinite = isfinite
    saved = simulator_module.torch
    simulator_module.torch = proxy
    try:
        yield
    finally:
        simulator_module.torch = saved


def _build(cfg, n: int, device: str, kind: str):
    torch.manual_seed(0)
    sim = Simulator(cfg).to(device).eval()
    sp = make_object(kind, n)
    with torch.no_grad():
        state = sim.init_state(sp, SceneContext.table())
    _sync(device)
    return sim, sp, state


def _block(sim, state0, actions, device, synced: bool) -> float:
    """ms per step over the actions, from state0."""
    state = state0
    if synced:
        state, times = timed_steps(sim, state, actions, device)
        out = statistics.median(times)
    else:
        with torch.no_grad():
            _sync(device)
            t = time.perf_counter()
            for a in actions:
                state = sim.step(state, a)
            _sync(device)
        out = (time.perf_counter() - t) * 1e3 / len(actions)
    if not bool(torch.isfinite(state.positions[0]).all()):
        raise RuntimeError("non-finite state after the timed block")
    return out


def _sync_sites(sim, state0, actions, device) -> Optional[dict]:
    """Host syncs in the steps (CUDA only): count per step and {file:line: count}."""
    if not str(device).startswith("cuda"):
        return None
    sites: dict[str, int] = {}
    state = state0
    with torch.no_grad():
        _sync(device)
        torch.cuda.set_sync_debug_mode("warn")
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                for a in actions:
                    state = sim.step(state, a)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    for w in caught:
        if "synchroniz" not in str(w.message):
            continue
        key = f"{w.filename.split('soma_ros/')[-1]}:{w.lineno}"
        sites[key] = sites.get(key, 0) + 1
    total = sum(sites.values())
    return dict(steps=len(actions), syncs=total, syncs_per_step=total / max(len(actions), 1),
                sites=dict(sorted(sites.items(), key=lambda kv: -kv[1])))


def finite_check_cost(model: str = "paper", n: int = 13000, device: str = "cuda", steps: int = 20,
                      blocks: int = 5, kind: str = "cloth") -> dict:
    """Step time with the finite check as is vs bypassed (see the module docstring)."""
    sim, sp, state0 = _build(load_model_config(model), n, device, kind)
    actions = _actions(sp, steps)
    # warm-up: one block of each
    _block(sim, state0, actions[:3], device, True)
    with bypass_finite_check():
        _block(sim, state0, actions[:3], device, True)
    res = {v: {"synced": [], "stream": []} for v in ("check", "bypass")}
    for b in range(blocks):
        order = ("check", "bypass") if b % 2 == 0 else ("bypass", "check")
        for v in order:
            for mode in ("synced", "stream"):
                if v == "bypass":
                    with bypass_finite_check():
                        res[v][mode].append(_block(sim, state0, actions, device, mode == "synced"))
                else:
                    res[v][mode].append(_block(sim, state0, actions, device, mode == "synced"))
    # the check alone, device idle
    with torch.no_grad():
        x = sim.step(state0, actions[0]).positions[0]
    alone = []
    for _ in range(200):
        _sync(device)
        t = time.perf_counter()
        ok = bool(torch.isfinite(x).all())
        alone.append((time.perf_counter() - t) * 1e3)
    assert ok
    out = dict(model=model, n_splats=n, device=str(device), kind=kind, steps_per_block=steps, blocks=blocks,
               sizes=sim.hierarchy.sizes, check_alone_ms=statistics.median(alone))
    for mode in ("synced", "stream"):
        c = statistics.median(res["check"][mode])
        p = statistics.median(res["bypass"][mode])
        out[mode] = dict(check_ms=c, bypass_ms=p, cost_ms=c - p, cost_pct=100.0 * (c - p) / c,
                         check_blocks=res["check"][mode], bypass_blocks=res["bypass"][mode])
    out["sync_debug"] = _sync_sites(sim, state0, actions[:5], device)
    return out


def physics_step(device: str, n: int = 1500, steps: int = 20, warmup: int = 3, kind: str = "rope",
                 train_config: str = "tiny_physics") -> dict:
    """Step time of the physics-prior model (the train config's model and object)."""
    from trainer.config import load_train_config

    tc = load_train_config(train_config)
    cfg = tc.model_config()
    sim, sp, state = _build(cfg, n, device, kind)
    state, times = timed_steps(sim, state, _actions(sp, warmup + steps), device, warmup)
    if not bool(torch.isfinite(state.positions[0]).all()):
        raise RuntimeError("physics_step: non-finite state")
    return dict(train_config=train_config, model=cfg.name, effects=[s.instance_key for s in sim.effects.specs],
                n_splats=n, kind=kind, device=str(device), sizes=sim.hierarchy.sizes,
                step_ms=statistics.median(times), step_min_ms=min(times), steps=len(times))


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu",
                    help="device of the finite-check measurement (default: cuda if available)")
    ap.add_argument("--model", default="paper")
    ap.add_argument("--splats", type=int, default=13000)
    ap.add_argument("--steps", type=int, default=20, help="steps per timed block")
    ap.add_argument("--blocks", type=int, default=5, help="timed blocks per variant (alternating)")
    ap.add_argument("--physics-devices", nargs="*", default=None,
                    help="devices for the physics-prior step (default: cpu, and cuda if available; none: skip)")
    ap.add_argument("--physics-splats", type=int, nargs="+", default=[1500])
    ap.add_argument("--physics-steps", type=int, default=20)
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    ap.add_argument("--json", dest="json_path", default=None)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    failed = False
    result: dict = dict(machine=machine_description(args.device), finite=None, physics=[], errors=[])
    print(result["machine"], flush=True)
    try:
        r = finite_check_cost(args.model, args.splats, args.device, args.steps, args.blocks)
        result["finite"] = r
        print(f"finite check, {r['model']} {r['n_splats']} splats on {r['device']} (levels {r['sizes']}), "
              f"median of {r['blocks']} blocks of {r['steps_per_block']} steps:")
        for mode in ("synced", "stream"):
            m = r[mode]
            print(f"  {mode:>6}: step {m['check_ms']:.2f} ms with the check, {m['bypass_ms']:.2f} ms bypassed: "
                  f"cost {m['cost_ms']:+.3f} ms ({m['cost_pct']:+.1f}% of the step)")
        print(f"  the check alone (device idle): {r['check_alone_ms']:.3f} ms")
        sd = r["sync_debug"]
        if sd is not None:
            print(f"  host syncs: {sd['syncs']} in {sd['steps']} steps ({sd['syncs_per_step']:.1f} per step); "
                  f"sites: {sd['sites']}")
    except Exception as exc:  # noqa: BLE001 - report and go on
        failed = True
        result["errors"].append(dict(section="finite", error=repr(exc), traceback=traceback.format_exc()))
        print("finite check FAILED:", flush=True)
        traceback.print_exc()
    pdevs = args.physics_devices
    if pdevs is None:
        pdevs = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for dev in pdevs:
        for n in args.physics_splats:
            try:
                r = physics_step(dev, n, args.physics_steps)
                result["physics"].append(r)
                print(f"physics prior ({r['train_config']}: {r['model']} + {', '.join(r['effects'])}), {r['kind']} "
                      f"{n} splats on {dev} (levels {r['sizes']}): step {r['step_ms']:.2f} ms "
                      f"(min {r['step_min_ms']:.2f}, median of {r['steps']})", flush=True)
            except Exception as exc:  # noqa: BLE001
                failed = True
                result["errors"].append(dict(section=f"physics {dev} {n}", error=repr(exc),
                                             traceback=traceback.format_exc()))
                print(f"physics prior on {dev} ({n} splats) FAILED:", flush=True)
                traceback.print_exc()
    if args.json_path:
        with open(args.json_path, "w") as f:
            json.dump(result, f, indent=1)
        print(f"wrote {args.json_path}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
