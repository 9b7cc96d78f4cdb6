"""Plots and markdown of the discrepancy workflow (:mod:`soma_ros.discrepancy.workflow`).

DIR/residual_time.png      3D residual and per-camera depth RMSE over time, per episode
DIR/residual_clusters.png  per-cluster residual displacement: |r| over (time, cluster) and a
                           top view of the clusters coloured by their mean residual with its
                           mean direction (where and when the model and the data disagree)
DIR/worst_frame.png        measured | simulated | |depth error| of the worst frame (largest 3D
                           residual) of the worst episode, per camera
DIR/ranking.png            explained fraction per candidate with its bootstrap interval
DIR/gap.png                held-out metrics before / after adding the named effect
DIR/residual_clusters.npz  per episode the [F, K, 3] cluster residuals and their frames
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _detection_line(det: dict | None, named: str) -> str:
    """The report's line on whether the measured data disagree beyond the model's own error."""
    if not det or not det.get("assessed"):
        n = 0 if not det else det.get("n_reference", 0)
        return (f"discrepancy beyond the model's own error: not assessed ({n} reference episodes; "
                f"at least 3 measured and 3 reference episodes (of the tasks both have) are needed)")
    verdict = "**detected**" if det["detected"] else "not detected"
    same = " of the same task" if det.get("stratified_by_task") else ""
    return (f"discrepancy beyond the model's own error: {verdict} (P(measured episode residual > reference{same}) = "
            f"{det['auc']:.2f}, lower bound {det['auc_low']:.2f}; median residual {1000 * det['measured_median']:.1f} mm "
            f"vs {1000 * det['reference_median']:.1f} mm on {det['n_reference']} reference episodes, "
            f"x{det['median_ratio']:.2f})"
            + ("; no candidate of the library explains it significantly" if det["detected"] and named == "none" else ""))


def _episode_table(per: dict, beyond: dict | None) -> list[str]:
    """Markdown: every measured episode, worst first, against the reference episodes of its task."""
    if not per:
        return []

    def x(v, key):
        r = v.get(key)
        return "n/a" if r is None else f"{r:.2f}"

    head = "Episodes, worst first (unchanged model; 3D residual = mean distance observed point -> nearest splat)"
    if beyond and any(v.get("reference_max") is not None for v in per.values()):
        head += (f": **{beyond['count']} of {len(per)} beyond the largest residual of the reference episodes of "
                 f"their task** (the model's own error), about {beyond['expected_by_chance']:.1f} expected by chance "
                 f"were the data like the reference" + (
                     f", P(at least {beyond['count']}) = {beyond['p_value']:.3f} (exact under exchangeability "
                     f"within each task); a pointer to where the disagreement is, not used by the decision"
                     if beyond.get("p_value") is not None else ""))
    lines = [head + ".", "",
             "| episode | task | split | 3D residual (mm) | depth RMSE (m) | x reference median | x largest reference |",
             "|---|---|---|---|---|---|---|"]
    for name, v in per.items():
        d = v.get("depth_rmse")
        ds = f"{d:.4f}" if isinstance(d, (int, float)) and math.isfinite(d) else "n/a"
        top = x(v, "vs_reference_max")
        top = f"**{top}**" if v.get("beyond_reference") else top
        lines.append(f"| {name} | {v.get('task')} | {v.get('split')} | {1000 * v['residual']:.1f} | {ds} | "
                     f"{x(v, 'vs_reference_median')} | {top} |")
    return lines + [""]


def write_report(out: Path, report: dict, stage1: dict, samples: dict, n_clusters: int, sim) -> None:
    import warnings

    warnings.filterwarnings("ignore", message="Mean of empty slice")
    plt = _plt()
    out = Path(out)
    names = list(stage1)
    # ---- residual over time
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    for n in names:
        r = stage1[n]
        ls = "-" if n in report["episodes"]["heldout"] else ":"
        ax[0].plot(r["frames"], 1000 * np.asarray(r["points"]), ls, label=f"{n} ({r['task']})")
        ax[1].plot(r["frames"], np.nanmean(np.asarray(r["depth_rmse"], dtype=float), axis=1), ls)
    ax[0].set_xlabel("frame")
    ax[0].set_ylabel("3D residual (mm): observed point -> nearest splat")
    ax[1].set_xlabel("frame")
    ax[1].set_ylabel("depth RMSE on object pixels (m), mean over cameras")
    ax[0].legend(fontsize=6, ncol=2)
    fig.suptitle("where in time: resimulated (original model) vs measured; solid = held-out, dotted = fit episodes")
    fig.tight_layout()
    fig.savefig(out / "residual_time.png", dpi=110)
    plt.close(fig)

    # ---- per-cluster residual motion
    stacks = [stage1[n]["cluster_residual"] for n in names]
    F = min(s.shape[0] for s in stacks)
    mag = np.stack([np.linalg.norm(s[:F], axis=-1) for s in stacks])  # [E, F, K]
    with np.errstate(all="ignore"):
        mean_mag = np.nanmean(mag, axis=0)  # [F, K]
        mean_vec = np.nanmean(np.stack([s[:F] for s in stacks]), axis=(0, 1))  # [K, 3]
    rest = sim.hierarchy.rest_positions[1].detach().cpu().numpy()
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    im = ax[0].imshow(1000 * mean_mag.T, aspect="auto", origin="lower", cmap="magma",
                      extent=[stage1[names[0]]["frames"][0], stage1[names[0]]["frames"][F - 1], -0.5, n_clusters - 0.5])
    ax[0].set_xlabel("frame")
    ax[0].set_ylabel("fine cluster")
    fig.colorbar(im, ax=ax[0], label="|residual displacement| (mm), mean over episodes")
    cm = np.nanmean(mean_mag, axis=0)
    sc = ax[1].scatter(rest[:, 0], rest[:, 1], c=1000 * cm, cmap="magma", s=30)
    ok = np.isfinite(mean_vec).all(axis=1)
    ax[1].quiver(rest[ok, 0], rest[ok, 1], mean_vec[ok, 0], mean_vec[ok, 1], color="tab:cyan", angles="xy")
    ax[1].set_aspect("equal")
    ax[1].set_xlabel("x (sim frame, m)")
    ax[1].set_ylabel("y (m)")
    fig.colorbar(sc, ax=ax[1], label="mean |residual| (mm)")
    ax[1].set_title("clusters at rest (G_0); arrows: mean residual (x, y)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "residual_clusters.png", dpi=110)
    plt.close(fig)
    np.savez_compressed(out / "residual_clusters.npz",
                        **{f"{n}__residual": stage1[n]["cluster_residual"] for n in names},
                        **{f"{n}__frames": np.asarray(stage1[n]["frames"]) for n in names})

    # ---- worst frame
    worst = max(names, key=lambda n: max(stage1[n]["points"]))
    w = stage1[worst]["worst"]
    if w is not None:
        C = w["gt_rgb"].shape[0]
        fig, ax = plt.subplots(C, 3, figsize=(9, 2.4 * C), squeeze=False)
        for c in range(C):
            ax[c, 0].imshow(w["gt_rgb"][c])
            ax[c, 1].imshow(w["sim_rgb"][c])
            imc = ax[c, 2].imshow(w["depth_error"][c], cmap="inferno", vmin=0, vmax=0.1)
            ax[c, 0].set_ylabel(stage1[worst]["cameras"][c], fontsize=8)
            for a in ax[c]:
                a.set_xticks([])
                a.set_yticks([])
        ax[0, 0].set_title("measured")
        ax[0, 1].set_title("simulated (original model)")
        ax[0, 2].set_title("|depth error| (m, 0..0.1)")
        fig.colorbar(imc, ax=ax[:, 2].tolist(), shrink=0.6)
        fig.suptitle(f"{worst}, frame {w['frame']} (largest 3D residual)", fontsize=9)
        fig.savefig(out / "worst_frame.png", dpi=100)
        plt.close(fig)

    # ---- ranking
    rk = report["ranking"]
    fig, ax = plt.subplots(figsize=(7, 3.6))
    x = np.arange(len(rk))
    e = np.asarray([r["explained_fraction"] for r in rk])
    lo = np.asarray([r["ci_low"] for r in rk])
    hi = np.asarray([r["ci_high"] for r in rk])
    has_load = bool(rk) and all("load_explained" in r for r in rk)
    wd = 0.4 if has_load else 0.8
    ax.bar(x - (wd / 2 if has_load else 0), e, width=wd, label="3D residual" if has_load else None,
           color=["tab:green" if r["name"] == report["named_effect"] else "tab:gray" for r in rk])
    ax.errorbar(x - (wd / 2 if has_load else 0), e, yerr=[np.maximum(e - lo, 0), np.maximum(hi - e, 0)], fmt="none",
                ecolor="k", capsize=4)
    if has_load:  # the wrist load's explained fraction beside it (clipped at the floor that counts in the score)
        le = np.asarray([max(r["load_explained"], -1.0) for r in rk])
        llo, lhi = np.asarray([r["load_ci_low"] for r in rk]), np.asarray([r["load_ci_high"] for r in rk])
        ax.bar(x + wd / 2, le, width=wd, color="tab:blue", alpha=0.6, label="wrist load")
        ax.errorbar(x + wd / 2, le, yerr=[np.maximum(le - llo, 0), np.maximum(lhi - le, 0)], fmt="none", ecolor="k",
                    capsize=4)
    ax.axhline(report["decision"]["min_explained"], color="tab:red", ls="--", lw=1, label="min explained (floor)")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(x, [r["name"] for r in rk], rotation=20)
    ax.set_ylabel("explained fraction (held-out)")
    ax.set_title(f"candidate ranking ({100 * (1 - 2 * report['decision']['alpha']):.0f}% bootstrap interval); "
                 f"named: {report['named_effect']}", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "ranking.png", dpi=110)
    plt.close(fig)

    # ---- gap
    gb, ga = report["gap_before"], report["gap_after"]
    mets = [m for m in ("rmse", "chamfer", "points", "abs_rel") if gb.get(m) is not None and ga.get(m) is not None]
    fig, ax = plt.subplots(1, max(1, len(mets)), figsize=(3 * max(1, len(mets)), 3), squeeze=False)
    for i, m in enumerate(mets):
        ax[0, i].bar([0, 1], [gb[m], ga[m]], color=["tab:gray", "tab:green"])
        ax[0, i].set_xticks([0, 1], ["before", "after"])
        ax[0, i].set_title(m, fontsize=9)
    fig.suptitle(f"held-out measured episodes, before / after adding {report['named_effect']}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "gap.png", dpi=110)
    plt.close(fig)

    # ---- markdown
    d = report["decision"]
    lines = [
        "# Discrepancy report",
        "",
        f"- checkpoint: `{report['checkpoint_in']}`",
        f"- measured data: `{report['data']}`; fit episodes {', '.join(report['episodes']['fit'])}; "
        f"held-out {', '.join(report['episodes']['heldout'])}",
        f"- **named effect: `{report['named_effect']}`** "
        f"(winner candidate `{d['winner_candidate']}`, lower bound {d['winner_lower_bound']:.3f} vs floor "
        f"{d['min_explained']}; margin over `{d.get('runner_up', '-')}` lower bound "
        f"{d.get('margin_lower_bound', float('nan')):.3f}; significant: {d['significant']})",
        f"- {_detection_line(report.get('discrepancy'), report['named_effect'])}",
        f"- updated model: `{report['checkpoint_out']}`",
        "",
        "## Where the residual lives",
        "",
        *_episode_table(report.get("episode_residuals") or {}, report.get("episodes_beyond_reference")),
        "![residual over time](residual_time.png)",
        "",
        "![per-cluster residual](residual_clusters.png)",
        "",
        "![worst frame](worst_frame.png)",
        "",
        "## Candidate ranking (held-out explained fraction of the 3D residual"
        + (", plus that of the wrist load: the score)" if has_load else ")"),
        "",
        "| candidate | explained | std (bootstrap) | interval | " + ("wrist load | score | " if has_load else "")
        + "fitted parameters |",
        "|---|---|---|---|" + ("---|---|" if has_load else "") + "---|",
    ]
    for r in rk:
        p = report["fits"][r["name"]]["parameters"]
        edge = set(report["fits"][r["name"]].get("at_bound", []))
        ps = ", ".join(f"{k}={np.round(v, 4).tolist()}{' (at its physical bound)' if k in edge else ''}"
                       for k, v in p.items())
        ld = (f"{r['load_explained']:+.3f} [{r['load_ci_low']:+.3f}, {r['load_ci_high']:+.3f}] | {r['score']:+.3f} | "
              if has_load else "")
        lines.append(f"| {r['name']} | {r['explained_fraction']:+.3f} | {r['uncertainty']:.3f} | "
                     f"[{r['ci_low']:+.3f}, {r['ci_high']:+.3f}] | {ld}{ps} |")
    lines += ["", "![ranking](ranking.png)", "", "## Gap on held-out measured episodes", "",
              "| metric | before | after | after / before |", "|---|---|---|---|"]
    for m in ("rmse", "chamfer", "points", "abs_rel", "psnr", "ssim"):
        b, a = gb.get(m), ga.get(m)
        ratio = f"{a / b:.3f}" if (a is not None and b not in (None, 0)) else "n/a"
        fb = "n/a" if b is None else f"{b:.5f}"
        fa = "n/a" if a is None else f"{a:.5f}"
        lines.append(f"| {m} | {fb} | {fa} | {ratio} |")
    lines += ["", "![gap](gap.png)", "",
              "Metric notes: " + "; ".join(f"{k}: {v}" for k, v in report["metric_notes"].items()), ""]
    (out / "report.md").write_text("\n".join(lines))
