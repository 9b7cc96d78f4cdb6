"""Benchmark of the simulator core: step time (and render time) versus splat count.

For each model config (``cpu``, ``paper``), device (CPU, and CUDA when
available) and splat count (1k, 4k, 13k) it builds a synthetic object, binds
the model (hierarchy built once; its time is reported as ``init``), then times
``Simulator.step`` under ``torch.no_grad`` with the robot's 30 control points
sweeping through the object (so the robot effect and the dynamic edges are
active). Render time is the forward time of a 320x240 frame of the same
number of splats, from :func:`benchmarks.bench_render.bench_render` (the
renderer's own benchmark scene).

Object: ``cloth`` (default; a 0.6 m x 0.6 m sheet: at 13k splats it has about
1,400 fine clusters, the order of the paper's cloth, so the network has real
work), ``rope`` (the synthetic rope: few clusters) or ``doll`` (an ellipsoidal
shell). Targets: ``cpu`` step at 13k splats <= 33 ms; 320x240 render of 13k
<= 100 ms forward.

Usage: ``soma bench core`` or ``python -m benchmarks.bench_core`` (same options).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from typing import Optional, Sequence

import torch

from soma_ros.core.config import load_model_config
from soma_ros.core.machine import machine_description
from soma_ros.core.simulator import RobotAction, SceneContext, Simulator
from soma_ros.core.splats import Splats

__all__ = ["make_object", "bench_step", "bench_render_rows", "machine_description", "run_core", "add_arguments", "run", "main"]

STEP_TARGET_MS = {"cpu": 33.0}
RENDER_TARGET_MS = 100.0


def make_object(kind: str, n: int, seed: int = 0) -> Splats:
    """A synthetic splat object of ``n`` splats resting on the table z = 0."""
    g = torch.Generator().manual_seed(seed)
    if kind == "cloth":
        side = 0.6
        uv = (torch.rand(n, 2, generator=g) - 0.5) * side
        z = 0.001 + 0.002 * torch.rand(n, generator=g)
        pts = torch.stack([uv[:, 0], uv[:, 1], z], dim=-1)
        scale = 0.7 * side / math.sqrt(n)
    elif kind == "rope":
        from soma_ros.core.scenes import synthetic_rope

        return synthetic_rope(n, seed=seed, center=(0.0, 0.0, 0.0))
    elif kind == "doll":
        d = torch.randn(n, 3, generator=g)
        d = d / d.norm(dim=-1, keepdim=True)
        pts = d * torch.tensor([0.08, 0.06, 0.15]) + torch.tensor([0.0, 0.0, 0.15])
        scale = 0.5 * math.sqrt(0.2 / n)
    else:
        raise ValueError(f"make_object: unknown kind {kind!r} (cloth, rope, doll)")
    colors = torch.rand(n, 3, generator=g)
    return Splats.from_points(pts, colors, scale=scale, opacity=0.8, total_mass=0.1)


def _sync(device) -> None:
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def timed_steps(sim, state, actions, device, warmup: int = 0):
    """Step ``sim`` from ``state`` through ``actions`` under no_grad, each step synced before and
    after; returns (the last state, ms of every step after the first ``warmup``)."""
    times = []
    with torch.no_grad():
        for i, a in enumerate(actions):
            _sync(device)
            t = time.perf_counter()
            state = sim.step(state, a)
            _sync(device)
            if i >= warmup:
                times.append((time.perf_counter() - t) * 1e3)
    return state, times


def _actions(sp: Splats, steps: int, seed: int = 0) -> list[RobotAction]:
    """30 control points (a 1 cm blob) sweeping across the object's top, gripper cycling."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = sp.means.min(0).values, sp.means.max(0).values
    centre = 0.5 * (lo + hi)
    blob = 0.01 * torch.randn(30, 3, generator=g)
    out = []
    for i in range(steps):
        ph = 2 * math.pi * i / max(steps, 1)
        c = centre + torch.tensor([0.3 * (hi[0] - lo[0]) * math.sin(ph), 0.2 * (hi[1] - lo[1]) * math.sin(2 * ph), 0.0])
        c[2] = hi[2]
        out.append(RobotAction(blob + c, 0.5 + 0.5 * math.sin(3 * ph)))
    return out


def bench_step(model: str, n: int, device: str = "cpu", steps: int = 20, warmup: int = 3, kind: str = "cloth") -> dict:
    """Time ``Simulator.step`` for one (model, n, device); returns a row dict."""
    cfg = load_model_config(model)
    torch.manual_seed(0)
    sim = Simulator(cfg).to(device).eval()
    sp = make_object(kind, n)
    scene = SceneContext.table()
    t0 = time.perf_counter()
    with torch.no_grad():
        state = sim.init_state(sp, scene)
    _sync(device)
    init_ms = (time.perf_counter() - t0) * 1e3
    state, times = timed_steps(sim, state, _actions(sp, warmup + steps), device, warmup)
    if not torch.isfinite(state.means).all():
        raise RuntimeError(f"bench_step: non-finite state ({model}, {n} splats)")
    h = sim.hierarchy
    e_fine = int(sim.graphs.static[1].shape[1])
    return dict(
        model=model, n_splats=n, device=str(device), kind=kind, sizes=h.sizes, fine_edges=e_fine,
        init_ms=init_ms, step_ms=statistics.median(times), step_min_ms=min(times), steps=len(times),
    )


def bench_render_rows(n_list: Sequence[int], device: str = "cpu", repeats: int = 3) -> dict[int, Optional[float]]:
    """{n: median forward ms of a 320x240 render}, via benchmarks.bench_render (None if unavailable)."""
    try:
        from benchmarks.bench_render import bench_render
    except ImportError as exc:  # pragma: no cover - renderer benchmark not in this checkout
        print(f"(render timing unavailable: {exc})")
        return {n: None for n in n_list}
    rows = bench_render(n_splats_list=list(n_list), resolutions=((320, 240),), device=device, repeats=repeats, warmup=1)
    return {r["n_splats"]: r["fwd_ms"] for r in rows}


def format_table(rows: list[dict], render: dict) -> str:
    hdr = (
        f"{'model':>6} {'device':>6} {'splats':>7} {'levels (nodes)':>22} {'fine edges':>10} "
        f"{'init ms':>8} {'step ms':>8} {'(min)':>7} {'target':>7} {'render ms':>10}"
    )
    lines = [hdr, "-" * len(hdr)]
    for r in rows:
        tgt = STEP_TARGET_MS.get(r["model"]) if r["n_splats"] == 13000 else None
        tgt_s = "-" if tgt is None else ("ok" if r["step_ms"] <= tgt else f">{tgt:.0f}")
        rd = render.get((r["device"], r["n_splats"]))
        rd_s = "-" if rd is None else f"{rd:.1f}" + ("" if r["n_splats"] != 13000 or rd <= RENDER_TARGET_MS else " (>100)")
        lines.append(
            f"{r['model']:>6} {r['device'][:6]:>6} {r['n_splats']:>7} {str(r['sizes']):>22} {r['fine_edges']:>10} "
            f"{r['init_ms']:>8.0f} {r['step_ms']:>8.1f} {r['step_min_ms']:>7.1f} {tgt_s:>7} {rd_s:>10}"
        )
    return "\n".join(lines)


def run_core(
    models: Sequence[str] = ("cpu", "paper"),
    splats: Sequence[int] = (1000, 4000, 13000),
    devices: Optional[Sequence[str]] = None,
    steps: int = 20,
    paper_steps: int = 3,
    kind: str = "cloth",
    render: bool = True,
    render_repeats: int = 3,
    json_path: Optional[str] = None,
) -> list[dict]:
    """Run the benchmark, print the machine and the table; returns the step rows.

    ``json_path``: also write the machine descriptions, the step rows and the render
    times ({device: {splats: fwd ms}}) there as JSON."""
    if devices is None:
        devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    rows: list[dict] = []
    render_ms: dict = {}
    machines: list[str] = []
    for dev in devices:
        machines.append(machine_description(dev))
        print(machines[-1], flush=True)
        for model in models:
            for n in splats:
                k = paper_steps if (model == "paper" and str(dev) == "cpu") else steps
                rows.append(bench_step(model, n, dev, steps=k, warmup=1 if k < 5 else 3, kind=kind))
                print(f"  {model} {n} on {dev}: step {rows[-1]['step_ms']:.1f} ms", flush=True)
        if render:
            for n, ms in bench_render_rows(splats, dev, render_repeats).items():
                render_ms[(str(dev), n)] = ms
    print(f"object: {kind}; step = Simulator.step under no_grad, median (min) of the timed steps "
          f"({steps}; paper on CPU {paper_steps}); render = 320x240 forward (benchmarks.bench_render)")
    print(format_table(rows, render_ms))
    if json_path:
        render_json: dict = {}
        for (dev, n), ms in render_ms.items():
            render_json.setdefault(dev, {})[str(n)] = ms
        with open(json_path, "w") as f:
            json.dump(dict(machines=machines, kind=kind, steps=steps, paper_steps=paper_steps,
                           rows=rows, render_fwd_ms_320x240=render_json), f, indent=1)
        print(f"wrote {json_path}")
    return rows


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--models", nargs="+", default=["cpu", "paper"], help="model configs (config/models)")
    p.add_argument("--splats", nargs="+", type=int, default=[1000, 4000, 13000])
    p.add_argument("--device", nargs="+", default=None, help="devices (default: cpu, and cuda if available)")
    p.add_argument("--steps", type=int, default=20, help="timed steps per row")
    p.add_argument("--paper-steps", type=int, default=3, help="timed steps for the paper model on CPU")
    p.add_argument("--object", dest="kind", default="cloth", choices=["cloth", "rope", "doll"])
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    p.add_argument("--no-render", action="store_true", help="skip render timing")
    p.add_argument("--json", dest="json_path", default=None, help="also write the rows to this JSON file")


def run(args: argparse.Namespace) -> int:
    if args.threads:
        torch.set_num_threads(args.threads)
    run_core(
        models=args.models, splats=args.splats, devices=args.device, steps=args.steps,
        paper_steps=args.paper_steps, kind=args.kind, render=not args.no_render,
        json_path=getattr(args, "json_path", None),
    )
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
