#!/usr/bin/env bash
# A time-boxed `paper` training run on a GPU, from a reference-world `paper`-preset rope dataset
# generated on the same machine, scored on the held-out episodes against `prior_only`.
#
# What it runs (each step under its own `timeout`; a failure is logged and the script goes on):
#   0. the machine (GPU, driver, python, torch);
#   1. soma world --object rope --preset paper --episodes $EPISODES --frames $FRAMES, one process per
#      episode (640x480, 3 cameras; 10 train / 4 test at 14 episodes);
#   2. soma train --config paper --max-minutes $MINUTES on cuda, validating every $IPE iterations on
#      3 training-split episodes (every 10th frame) instead of the paper's 200 / 10 / 5;
#   3. soma eval of the kept checkpoint and of the same weights with the network off (--prior-only)
#      on the test split, at the same time, every 2nd frame;
#   4. a table: iterations per second, the validation curve, held-out figures.
# Output: $OUT/log.txt and $OUT/run.tar.gz (log.csv, val_tasks.csv/.png, loss.png, summary.json,
# the two evaluations' JSON). $OUT defaults to runs/gpu_train; the dataset and run go to a temporary
# folder ($WORK, default from mktemp).
#
# From the repository root, with the packages of `make setup` (or carried wheels in .whl/ and the
# GL loaders in .gl/, which the script installs first when present):
#   OUT=DIR bash benchmarks/gpu_train.sh
# Optional: PYTHON (python3), EPISODES (14), FRAMES (100), MINUTES (4), IPE (40), QUICK=1 (a CPU
# smoke test: tiny preset, cpu device, a few seconds of training).
set -u
set -o pipefail

cd "$(dirname "$0")/.."
OUT="${OUT:-runs/gpu_train}"
mkdir -p "$OUT"
PY="${PYTHON:-python3}"
WORK="${WORK:-$(mktemp -d)}"
SITE="$WORK/site"; mkdir -p "$WORK"
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" MUJOCO_GL=egl
if ls .gl/*.deb >/dev/null 2>&1; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
    [ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ] \
        && export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
fi
if ls .whl/*.whl >/dev/null 2>&1; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl \
        && export PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"

if [ "${QUICK:-0}" = 1 ]; then
    PRESET=tiny; EPISODES="${EPISODES:-6}"; FRAMES="${FRAMES:-12}"; MINUTES="${MINUTES:-0.2}"; IPE="${IPE:-2}"
    DEVICE=cpu; EXTRA="--set scene.num_splats=500 --set scene.photometric_iters=2 --set model_overrides.gnn.layers=2"
else
    PRESET=paper; EPISODES="${EPISODES:-14}"; FRAMES="${FRAMES:-100}"; MINUTES="${MINUTES:-4}"; IPE="${IPE:-40}"
    DEVICE=cuda; EXTRA=""
fi
DATA="$WORK/data"; RUN="$WORK/run"
SOMA=("$PY" -m soma_ros.cli)

section() { echo; echo "=== $* ($(date +%T), ${SECONDS}s)"; }

main() {
    section "machine"
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv 2>/dev/null || echo "(no nvidia-smi)"
    echo "CPU: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2-) | nproc $(nproc) | commit $(git rev-parse --short HEAD 2>/dev/null || echo '?')"
    "$PY" -c "import sys, torch; print('python', sys.version.split()[0], '| torch', torch.__version__, '| cuda', torch.cuda.is_available())"
    rm -rf "$DATA" "$RUN"

    section "1. soma world: rope, preset $PRESET, $EPISODES episodes of $FRAMES frames"
    timeout 240 "${SOMA[@]}" world --object rope --preset "$PRESET" --episodes "$EPISODES" --frames "$FRAMES" \
        --workers "$EPISODES" --out "$DATA" --quiet || echo "soma world FAILED (rc $?)"

    section "2. soma train --config paper on $DEVICE for at most $MINUTES min"
    # shellcheck disable=SC2086
    timeout $(( ${MINUTES%.*} * 60 + 240 )) "${SOMA[@]}" train --data "$DATA" --config paper --out "$RUN" --quiet \
        --max-minutes "$MINUTES" --set device="$DEVICE" --set schedule.iters_per_epoch="$IPE" \
        --set optim.network.warmup_iters="$IPE" --set run.checkpoint_every="$IPE" --set run.val_episodes=3 \
        --set run.val_frame_stride=10 $EXTRA > "$WORK/train.json" || echo "soma train FAILED (rc $?)"
    grep -v '^ *"\(val_history\|train_episodes\)' "$WORK/train.json" | head -c 4000; echo

    section "3. soma eval: kept checkpoint and prior_only, test split"
    timeout 200 "${SOMA[@]}" eval --checkpoint "$RUN" --data "$DATA" --split test --frame-stride 2 --no-lpips \
        --no-sheets --quiet --out "$WORK/eval_full" > "$WORK/eval_full.txt" 2>&1 &
    timeout 200 "${SOMA[@]}" eval --checkpoint "$RUN" --data "$DATA" --split test --frame-stride 2 --no-lpips \
        --no-sheets --quiet --prior-only --out "$WORK/eval_prior" > "$WORK/eval_prior.txt" 2>&1 &
    wait
    tail -n 15 "$WORK/eval_full.txt" "$WORK/eval_prior.txt"

    section "4. summary"
    "$PY" - "$RUN" "$WORK" <<'EOF' || echo "summary FAILED"
import csv, json, sys
from pathlib import Path
run, work = Path(sys.argv[1]), Path(sys.argv[2])
s = json.loads((run / "summary.json").read_text())
rows = list(csv.DictReader(open(run / "log.csv")))
train = [r for r in rows if r["kind"] == "train"]
secs = sum(float(r["seconds"]) for r in train)
print(f"iterations {s['iterations']} in a {s.get('loop_seconds')} s loop (timed out: {s.get('timed_out')}); "
      f"{len(train) / max(secs, 1e-9):.2f} training iterations/s excluding validation, "
      f"{s['iterations'] / max(s.get('loop_seconds') or 1, 1e-9):.2f} including it")
print("validation: iteration, val_loss, img, depth (m), points (m), score")
for h in s["val_history"]:
    print(f"  {h['iteration']:5d} {h['val_loss']:.5f} {h['img']:.5f} {h['depth']:.5f} {h['points']:.5f} {h['score']:.4f}")
print(f"kept iteration {s['best_iteration']} (score {s['kept_score']})")
for name in ("eval_full", "eval_prior"):
    for f in sorted((work / name).glob("*.json")):
        print(name, f.name, f.read_text()[:1500])
EOF
    tar -czf "$OUT/run.tar.gz" -C "$WORK" --ignore-failed-read run/log.csv run/val_tasks.csv run/val_tasks.png \
        run/loss.png run/summary.json run/train_config.yaml train.json eval_full eval_prior eval_full.txt \
        eval_prior.txt 2>/dev/null
    section "done"
}

main 2>&1 | tee "$OUT/log.txt"
