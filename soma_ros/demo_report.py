"""The `make demo` report: live-run statistics, held-out metrics and a contact sheet."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np


def _read_live(bag: Path, cams: Sequence[str]) -> dict:
    from .core.cloud_layout import cloud_to_records
    from .data.bags import check_interface_versions, open_reader

    out: dict = {"status": [], "js": [], "images": {c: [] for c in cams}, "splat_counts": []}
    r = open_reader(bag)
    try:
        check_interface_versions(r, bag)
        for conn, t, raw in r.messages():
            m = r.deserialize(raw, conn.msgtype)
            stamp = int(m.header.stamp.sec) * 10**9 + int(m.header.stamp.nanosec)
            if conn.topic == "/soma/status":
                out["status"].append(m)
            elif conn.topic == "/joint_states":
                out["js"].append(stamp)
            elif conn.topic == "/soma/splats":
                out["splat_counts"].append(len(cloud_to_records(m)))
            else:
                for c in cams:
                    if conn.topic == f"/soma/{c}/image_raw":
                        img = np.asarray(m.data, dtype=np.uint8).reshape(m.height, m.width, 3)
                        out["images"][c].append((stamp, img))
    finally:
        r.close()
    return out


def write_report(out: Path, held_bag: Path, live_bag: Path, eval_dir: Path, cams: Sequence[str], seconds: float) -> Path:
    import cv2

    from soma_ros.data.bags import read_episode

    live = _read_live(live_bag, cams)
    meas = read_episode(held_bag, cameras=list(cams))
    st = [s for s in live["status"] if s.state == "running"]
    stats = {
        "steps": int(st[-1].step) if st else 0,
        "step_rate_hz_median": float(np.median([s.step_rate_hz for s in st])) if st else 0.0,
        "image_rate_hz_median": float(np.median([s.image_rate_hz for s in st])) if st else 0.0,
        "step_time_ms_median": float(np.median([s.step_time_ms for s in st])) if st else 0.0,
        "render_time_ms_median": float(np.median([s.render_time_ms for s in st])) if st else 0.0,
        "joint_state_lag_ms_median": float(np.median([s.joint_state_lag_ms for s in st])) if st else 0.0,
        "joint_states_received": int(live["status"][-1].joint_states_received) if live["status"] else 0,
        "joint_states_rejected": int(live["status"][-1].joint_states_rejected) if live["status"] else 0,
        "images_recorded": {c: len(v) for c, v in live["images"].items()},
        "splat_clouds_recorded": len(live["splat_counts"]),
    }

    # Pair live images with measured frames through the replayed joint states' clock.
    rows = []
    if live["js"]:
        t0 = min(live["js"])
        b0 = int(meas.stamps_ns[0])
        T = meas.num_frames
        picks = np.linspace(0, T - 1, 5).round().astype(int)
        for f in picks:
            target = t0 + int(meas.stamps_ns[f]) - b0
            row = []
            for c in cams:
                imgs = live["images"][c]
                if not imgs:
                    continue
                k = int(np.argmin([abs(s - target) for s, _ in imgs]))
                sim = imgs[k][1]
                cs = meas.cameras[c]
                keep = cs.object_mask[f] & ~(cs.robot_mask[f] if cs.robot_mask is not None else False)
                gt = (cs.rgb[f] * keep[..., None]).astype(np.uint8)  # the paper's masking: object only
                if sim.shape != gt.shape:
                    sim = cv2.resize(sim, (gt.shape[1], gt.shape[0]), interpolation=cv2.INTER_AREA)
                err = np.abs(sim.astype(np.int16) - gt.astype(np.int16)).mean(-1).clip(0, 255).astype(np.uint8)
                heat = cv2.applyColorMap(err * 3, cv2.COLORMAP_INFERNO)[..., ::-1]
                row.append(np.concatenate([gt, sim, heat], axis=1))
            if row:
                rows.append(np.concatenate(row, axis=1))
    sheet_path = out / "contact_sheet.png"
    if rows:
        sheet = np.concatenate(rows, axis=0)
        cv2.imwrite(str(sheet_path), sheet[..., ::-1])

    metrics = {}
    mp = eval_dir / "metrics.json"
    if mp.is_file():
        metrics = json.loads(mp.read_text())
    (out / "report.json").write_text(json.dumps({"live": stats, "eval": metrics, "seconds": seconds}, indent=2, default=float))
    lines = [
        "# soma_ros demo report", "",
        f"Held-out episode `{held_bag.name}` replayed into `soma_sim_node` by `soma_bag_player`; "
        f"total demo time {seconds:.0f} s.", "",
        "## Live run (from /soma/status)", "", "| quantity | value |", "|---|---|",
        *[f"| {k} | {v} |" for k, v in stats.items()], "",
        "## Open-loop evaluation on held-out episodes (`soma eval`)", "",
    ]
    table = eval_dir / "table.md"
    lines += [table.read_text() if table.is_file() else "(no evaluation table)", ""]
    lines += ["## Contact sheet", "",
              "Each row a frame of the held-out episode; per camera: measured x object mask (robot pixels removed) | "
              "live simulation | |error| heat map.", "",
              f"![contact sheet]({sheet_path.name})", ""]
    rp = out / "report.md"
    rp.write_text("\n".join(lines))
    return rp
