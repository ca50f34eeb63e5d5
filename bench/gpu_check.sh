#!/usr/bin/env bash
# The GPU check: the odometry front end of the `cpu` and `paper` presets on CUDA, on a short
# synthetic room loop and on the first 7-Scenes kitchen frames, timed against the CP-SLAM
# paper's figures. Meant for a machine with one NVIDIA GPU and no package index: what the
# image lacks comes as wheels in WHEELS (bench/gpu_prepare.sh makes them), the kitchen frames
# in a folder brought along. Finishes in under 8 minutes (BUDGET_S, default 450 s, the wheel
# install included): every run stops at its own time budget (bench/odometry.py --max-seconds,
# checked between frames), is killed at what is left of the whole budget, and reports the
# frames it did; the table comes last.
#
# First the device-placement tests (their `cuda` cases run only where a GPU is); then the
# runs, in this order (preset, sequence, frames at most, seconds at most):
#   cpu    synthetic room loop, 320x240      60 frames   40 s   (.gpudata/room-0-loop)
#   paper  7-Scenes kitchen, 640x480        100 frames  140 s
#   paper  synthetic room loop, 320x240      60 frames  100 s
#   cpu    7-Scenes kitchen, 320x240        100 frames   50 s
# each its own bench/odometry.py process (--device cuda, one torch thread count, run.seed 0,
# --loops off: the front end the table times; the loop closure's back end needs gtsam and
# zstandard, which the GPU machine's image lacks).
#
# Usage: bench/gpu_check.sh [KITCHEN_DIR]
# Environment: CPSLAM_GPU_KITCHEN (default .gpudata/7scenes-kitchen), CPSLAM_GPU_SYNTH
#   (.gpudata/room-0-loop: rendered by bench/gpu_prepare.sh, since rendering needs open3d;
#   without it bench/odometry.py renders its first scene), CPSLAM_GPU_WHEELS
#   (.whl), CPSLAM_GPU_DEVICE (cuda), CPSLAM_GPU_BUDGET_S (450), CPSLAM_GPU_SYNTH_FRAMES (60),
#   CPSLAM_GPU_REAL_FRAMES (100), CPSLAM_GPU_SCALE (1: multiplies every run's seconds),
#   CPSLAM_GPU_PRESETS ("cpu paper": the presets whose runs are done), CPSLAM_GPU_SET
#   (config overrides a.b=v for every run, space-separated; none by default),
#   PYTHON (python3), OUT (where the JSON, the table and the log go; runs/gpu-check if unset).
# Example (the device tool, carry [".whl", ".gpudata"]): bash bench/gpu_check.sh
set -uo pipefail

START=$SECONDS
REPO=$(cd "$(dirname "$0")/.." && pwd)
cd "$REPO"
KITCHEN=${1:-${CPSLAM_GPU_KITCHEN:-.gpudata/7scenes-kitchen}}
SYNTH=${CPSLAM_GPU_SYNTH:-.gpudata/room-0-loop}
WHEELS=${CPSLAM_GPU_WHEELS:-.whl}
DEVICE=${CPSLAM_GPU_DEVICE:-cuda}
BUDGET_S=${CPSLAM_GPU_BUDGET_S:-450}
SYNTH_FRAMES=${CPSLAM_GPU_SYNTH_FRAMES:-60}
REAL_FRAMES=${CPSLAM_GPU_REAL_FRAMES:-100}
SCALE=${CPSLAM_GPU_SCALE:-1}
PRESETS=${CPSLAM_GPU_PRESETS:-cpu paper}
read -r -a OVERRIDES <<< "${CPSLAM_GPU_SET:-}"
PY=${PYTHON:-python3}
RESULTS=${OUT:-$REPO/runs/gpu-check}
SITE=$(mktemp -d /tmp/cpslam-gpu.XXXXXX)
export PYTHONUNBUFFERED=1
mkdir -p "$RESULTS"
exec > >(tee "$RESULTS/gpu_check.log") 2>&1

echo "== gpu_check: device $DEVICE, budget ${BUDGET_S} s, kitchen $KITCHEN, wheels $WHEELS"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,driver_version \
  --format=csv,noheader

# (a) What the image lacks, from the wheels; cpslam itself from this checkout (gpu_env.sh).
# shellcheck source=bench/gpu_env.sh
source bench/gpu_env.sh || exit 1
"$PY" -P - "$DEVICE" <<'EOF' || { echo "gpu_check: the environment is not usable"; exit 1; }
import sys

import numpy
import pydantic
import torch

import cpslam.agent.odometry  # noqa: F401

heavy = sorted(m for m in ("zenoh", "gtsam", "open3d") if m in sys.modules)
if heavy:
    sys.exit(f"importing the odometry pulled {heavy}")
print(f"python {sys.version.split()[0]}, torch {torch.__version__}, numpy {numpy.__version__}, "
      f"pydantic {pydantic.VERSION}, cpslam from {cpslam.__file__}")
if sys.argv[1].startswith("cuda"):
    if not torch.cuda.is_available():
        sys.exit("CUDA is not available to torch")
    print(f"GPU: {torch.cuda.get_device_name(0)}, "
          f"{torch.cuda.get_device_properties(0).total_memory / 2**30:.1f} GiB")
EOF

# The device tests (tests/integration/test_device_odometry.py has a `cuda` case for this).
# -P: the checkout's own cpslam/ folder must not shadow the laid-out package.
echo "== device tests"
timeout 150 "$PY" -P -m pytest -q -p no:cacheprovider tests/unit/test_device.py \
  tests/unit/test_device_placement.py tests/integration/test_device_odometry.py 2>&1 | tail -n 15

CORES=$(nproc)
THREADS=$((CORES < 8 ? CORES : 8))
DATA_ARGS=(--real "$KITCHEN")
[ -d "$SYNTH" ] && DATA_ARGS+=(--synth "$SYNTH")
if [ ! -d "$KITCHEN" ]; then
  echo "gpu_check: no kitchen frames at $KITCHEN: the real runs are skipped"
fi

# (b) One bench run: its soft budget is its own seconds or what the whole budget leaves
# (less a minute for the last frame, the accuracy and the table), its hard limit what the
# whole budget leaves.
run_one() {
  local preset=$1 only=$2 frames=$3 want=$4
  local file="$RESULTS/$preset-$only.json"
  local left=$((BUDGET_S - (SECONDS - START) - 10))
  local secs
  secs=$(awk -v w="$want" -v s="$SCALE" -v l="$left" \
    'BEGIN { x = w * s; if (x > l - 60) x = l - 60; printf "%d", x }')
  if [ "$secs" -lt 15 ]; then
    printf '{"preset": "%s", "only": "%s", "failed": "skipped: %d s left of the budget"}\n' \
      "$preset" "$only" "$left" > "$file"
    return
  fi
  echo "== $preset / $only: up to $frames frames, ${secs} s (hard limit ${left} s)"
  timeout --kill-after=5 "$left" "$PY" bench/odometry.py --preset "$preset" --only "$only" \
    --frames "$frames" --scenes 1 --threads "$THREADS" --jobs 1 --device "$DEVICE" --loops off \
    "${DATA_ARGS[@]}" --max-seconds "$secs" --set "${OVERRIDES[@]}" --json "$file.tmp" \
    > "$RESULTS/$preset-$only.out"
  local rc=$?
  tail -n 4 "$RESULTS/$preset-$only.out"
  rm -f "$RESULTS/$preset-$only.out"
  if [ $rc -eq 0 ] && [ -s "$file.tmp" ]; then
    mv "$file.tmp" "$file"
  else
    rm -f "$file.tmp"
    local why="exit code $rc"
    [ $rc -eq 124 ] || [ $rc -eq 137 ] && why="killed at the hard limit of $left s"
    printf '{"preset": "%s", "only": "%s", "failed": "%s"}\n' "$preset" "$only" "$why" \
      > "$file"
  fi
}

REPORTS=()
for run in "cpu synth $SYNTH_FRAMES 40" "paper real $REAL_FRAMES 140" \
           "paper synth $SYNTH_FRAMES 100" "cpu real $REAL_FRAMES 50"; do
  read -r preset only frames seconds <<< "$run"
  case " $PRESETS " in *" $preset "*) ;; *) continue ;; esac
  run_one "$preset" "$only" "$frames" "$seconds"
  REPORTS+=("$RESULTS/$preset-$only.json")
done

# (c) The table, beside the paper's figures; one JSON with all of it.
echo "== results ($((SECONDS - START)) s so far)"
"$PY" bench/gpu_report.py "${REPORTS[@]}" --json "$RESULTS/gpu_check.json"
rm -f "${REPORTS[@]}"
rm -rf "$SITE"
echo "== gpu_check done in $((SECONDS - START)) s"
