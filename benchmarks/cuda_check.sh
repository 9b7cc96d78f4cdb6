#!/usr/bin/env bash
# CUDA check of the simulator core: what `soma bench core` and the renderer benchmark measure on
# a GPU, next to the same machine's CPU, plus what the per-step finite check costs there.
#
# What it runs (in this order, the GPU parts first; each under its own `timeout`, and a failure
# is logged with its traceback and the script goes on):
#   0. the machine: nvidia-smi -L, the GPU's driver/memory/clocks, python, torch and its CUDA,
#      the device name, CPU model and core count;
#   1. python -m benchmarks.bench_core on cuda: models cpu and paper, 1k/4k/13k splats (cloth),
#      20 timed steps per row, each step synced before and after; 320x240 render forward per size;
#   3. python -m benchmarks.bench_render on cuda (320x240 and 640x480, forward and forward+backward);
#   4. python -m benchmarks.bench_core on cpu with $THREADS torch threads (default: all cores) and
#      with 1 thread (the README's figures are 1 thread), paper model 3 timed steps;
#   5. python -m benchmarks.bench_render on cpu with $THREADS threads (ratio to step 3).
# Without CUDA (torch.cuda.is_available() False) steps 1-3 run their CPU parts only or are skipped,
# so the script also runs end to end on a CPU-only machine (a smoke test; QUICK=1 shrinks it).
#
# Output: everything is tee'd to $OUT/log.txt; JSON rows go to $OUT/*.json (6 files in all).
# $OUT defaults to /tmp/cuda_check_out.
#
# How to run, from the repository root (no install needed; the core needs torch, numpy, scipy,
# pyyaml, all in a stock CUDA PyTorch image):
#   OUT=/tmp/cuda_check bash benchmarks/cuda_check.sh
# On this workplace's lent GPU machine (device tool), as one call:
#   run(command="bash benchmarks/cuda_check.sh", timeout_s=420)
# Optional: PYTHON (default python3), THREADS (default nproc), QUICK=1 (few steps, small sizes).
# If a `.whl/` folder with wheels is present they are installed to /tmp/site first (carried
# wheels for packages the machine lacks; none are needed by what this script imports).
set -u
set -o pipefail

cd "$(dirname "$0")/.."
OUT="${OUT:-/tmp/cuda_check_out}"
mkdir -p "$OUT"
PY="${PYTHON:-python3}"
THREADS="${THREADS:-$(nproc)}"
export PYTHONUNBUFFERED=1
if ls .whl/*.whl >/dev/null 2>&1; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        && export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"

if [ "${QUICK:-0}" = 1 ]; then
    SPLATS="1000 4000"; STEPS=3; PAPER_STEPS=1
    RENDER_SPLATS="1000 4000"; REPEATS=1
else
    SPLATS="1000 4000 13000"; STEPS=20; PAPER_STEPS=3
    RENDER_SPLATS="1000 4000 13000"; REPEATS=5
fi

section() { echo; echo "=== $* ($(date +%T), ${SECONDS}s)"; }

main() {
    section "machine"
    nvidia-smi -L 2>&1 || echo "(no nvidia-smi)"
    nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm,temperature.gpu,utilization.gpu \
        --format=csv 2>/dev/null || true
    echo "CPU: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2-) | nproc $(nproc) | torch threads used: $THREADS"
    "$PY" - <<'EOF'
import sys, torch, numpy, scipy
print("python", sys.version.split()[0], "| torch", torch.__version__, "| torch CUDA", torch.version.cuda,
      "| cudnn", torch.backends.cudnn.version(), "| numpy", numpy.__version__, "| scipy", scipy.__version__)
print("cuda available:", torch.cuda.is_available())
if torch.cuda.is_available():
    p = torch.cuda.get_device_properties(0)
    print("device:", torch.cuda.get_device_name(0), "| capability", torch.cuda.get_device_capability(0),
          "| SMs", p.multi_processor_count, "| memory %.1f GiB" % (p.total_memory / 2**30))
print("float32 matmul precision:", torch.get_float32_matmul_precision(), "| tf32 matmul:",
      torch.backends.cuda.matmul.allow_tf32)
try:
    import gsplat  # noqa: F401
    print("gsplat: present (render backend auto -> gsplat on CUDA)")
except Exception as exc:
    print("gsplat: absent (%s): the renderer uses its torch path on CUDA too" % type(exc).__name__)
EOF
    "$PY" -c "import benchmarks.bench_core, benchmarks.bench_render, soma_ros.training.config; print('imports ok')" \
        || echo "IMPORT FAILED"
    local has_cuda
    has_cuda=$("$PY" -c "import torch; print(int(torch.cuda.is_available()))" 2>/dev/null || echo 0)

    if [ "$has_cuda" = 1 ]; then
        section "1. bench_core on cuda (threads $THREADS)"
        timeout 200 "$PY" -m benchmarks.bench_core --models cpu paper --splats $SPLATS --device cuda \
            --steps $STEPS --threads "$THREADS" --json "$OUT/bench_core_cuda.json" || echo "bench_core cuda FAILED (rc $?)"
    else
        section "1. bench_core on cuda: skipped (no CUDA)"
    fi

    if [ "$has_cuda" = 1 ]; then
        section "3. bench_render on cuda"
        timeout 120 "$PY" -m benchmarks.bench_render --device cuda --repeats $REPEATS --threads "$THREADS" \
            --splats $RENDER_SPLATS --json "$OUT/bench_render_cuda.json" || echo "bench_render cuda FAILED (rc $?)"
    else
        section "3. bench_render on cuda: skipped (no CUDA)"
    fi

    section "4a. bench_core on cpu, $THREADS threads"
    timeout 150 "$PY" -m benchmarks.bench_core --models cpu paper --splats $SPLATS --device cpu --steps $STEPS \
        --paper-steps $PAPER_STEPS --threads "$THREADS" --json "$OUT/bench_core_cpu_t$THREADS.json" \
        || echo "bench_core cpu FAILED (rc $?)"
    if [ "$THREADS" != 1 ]; then
        section "4b. bench_core on cpu, 1 thread"
        timeout 150 "$PY" -m benchmarks.bench_core --models cpu paper --splats $SPLATS --device cpu --steps $STEPS \
            --paper-steps $PAPER_STEPS --threads 1 --json "$OUT/bench_core_cpu_t1.json" \
            || echo "bench_core cpu 1 thread FAILED (rc $?)"
    fi

    section "5. bench_render on cpu, $THREADS threads"
    timeout 150 "$PY" -m benchmarks.bench_render --device cpu --repeats 3 --threads "$THREADS" \
        --splats $RENDER_SPLATS --json "$OUT/bench_render_cpu.json" || echo "bench_render cpu FAILED (rc $?)"

    section "done"
}

main 2>&1 | tee "$OUT/log.txt"
