"""Side views of a model's held-out rollouts against the reference world's rope, frame by frame.

    python -m benchmarks.rope_side_view --run RUN --data MEASURED --out FIG.png \
        [--episodes rope_001,rope_004,rope_008] [--frames 40,50,60,79] [--config physics] \
        [--variants '{"m10": [{"name": "mass_scale", "excess": 9.0}]}']

One row per episode, one panel per frame: the model's splat centres (orange; with ``--variants``,
the model with those effect terms added, as ``benchmarks.discrepancy_terms`` sets them, in further
colours) and the world's rope vertices (blue, the ground-truth topic: EVALUATION ONLY), seen from the side, in the vertical plane
through the rope's first-to-last vertex direction at frame 0 with the fingers' centre (the TCP,
black cross) at the origin. The rollouts are the discrepancy workflow's (held-out split, its config:
``benchmarks.discrepancy_terms.build_models``), so the picture is of the rollouts its gap is
measured on. Where a rope's held arm leaves the fingers and where it kinks is what a number
like the depth RMSE hides.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def side_view(run: Path, data: Path, out: Path, episodes: list[str], frames: list[int], config: str = "physics",
              variants: dict | None = None) -> Path:
    """Draw the figure (module docstring) to ``out``; returns it. ``variants``: {name: [effect spec, ...]}
    (``benchmarks.discrepancy_terms.parse_variants``), drawn beside the model as trained."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from benchmarks.discrepancy_terms import UNCHANGED, build_models
    from trainer.discrepancy import HELDOUT
    from trainer.evaluate_gt import read_ground_truth_points

    ctx, _, models = build_models(run, data, variants or {}, config)
    refs = {r.name: r for r in ctx.episodes(HELDOUT)}
    missing = [e for e in episodes if e not in refs]
    if missing:
        raise ValueError(f"not held-out episodes of {data}: {missing} (held out: {sorted(refs)})")
    fig, axs = plt.subplots(len(episodes), len(frames), figsize=(4.2 * len(frames), 3.6 * len(episodes)), squeeze=False)
    for r, name in enumerate(episodes):
        ep, init = ctx.store.episode(name), ctx.store.initial_splats(name)
        bad = [t for t in frames if not 0 <= t < ep.num_frames]
        if bad:
            raise ValueError(f"{name}: frames {bad} outside 0..{ep.num_frames - 1}")
        world = read_ground_truth_points(data / name)  # [T, M, 3]
        sims = {k: [s[0] for s in m.rollout(ep, init, ctx.scene)] for k, m in models.items()}
        axis = world[0][-1, :2] - world[0][0, :2]
        axis = axis / max(float(np.linalg.norm(axis)), 1e-9)
        for c, t in enumerate(frames):
            tcp = ep.control_points[t].mean(0).numpy()
            w = world[t]
            ax = axs[r, c]
            for k, (key, sim) in enumerate(sims.items()):
                s = sim[t].detach().double().numpy()
                label = "model's splats" if key == UNCHANGED else f"with {key}"
                ax.scatter((s[:, :2] - tcp[:2]) @ axis, s[:, 2], s=2, c=COLOURS[k % len(COLOURS)], label=label)
            ax.plot((w[:, :2] - tcp[:2]) @ axis, w[:, 2], "b.-", ms=4, lw=1, label="world's rope")
            ax.plot([0.0], [tcp[2]], "k+", ms=14, label="fingers (TCP)")
            ax.set_title(f"{name}, frame {t}")
            ax.set_aspect("equal")
            ax.set_xlabel("along the rope (m)")
            ax.set_ylabel("height (m)")
    axs[0, 0].legend(loc="lower left", fontsize=8)
    fig.suptitle(f"{run.name} on {data.name}: held-out rollouts, side view", y=1.0)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=55)
    plt.close(fig)
    return out


COLOURS = ("tab:orange", "tab:red", "tab:green", "tab:purple", "tab:brown")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.rope_side_view", description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", required=True, type=Path, help="soma train run folder")
    ap.add_argument("--data", required=True, type=Path, help="measured dataset with the ground-truth topic")
    ap.add_argument("--out", required=True, type=Path, help="the figure (.png)")
    ap.add_argument("--episodes", default="rope_001,rope_004,rope_008", help="held-out episodes, comma-separated")
    ap.add_argument("--frames", default="40,50,60,79", help="frames, comma-separated")
    ap.add_argument("--config", default="physics", help="workflow config (config/discrepancy)")
    ap.add_argument("--variants", default=None, metavar="JSON",
                    help='also draw the model with these effect terms: {"name": [effect spec, ...], ...}')
    a = ap.parse_args(argv)
    try:
        frames = [int(f) for f in a.frames.split(",")]
    except ValueError:
        ap.error(f"--frames: integers, comma-separated; got {a.frames!r}")
    try:
        from benchmarks.discrepancy_terms import parse_variants

        variants = parse_variants(a.variants) if a.variants else None
        out = side_view(a.run, a.data, a.out, [e for e in a.episodes.split(",") if e], frames, a.config, variants)
    except (ValueError, FileNotFoundError) as e:  # incl. an unknown effect (ConfigError) or bad --variants
        print(f"rope_side_view: {e}", file=sys.stderr)
        return 2
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
