#!/usr/bin/env bash
# Prepares bench/gpu_check.sh's luggage, here (with network), in the checkout that travels to
# the GPU machine:
#   .whl/      the wheels of the Python packages the odometry bench imports that the GPU
#              machine's image lacks (pydantic and its needs), for CPython 3.12 manylinux
#              x86_64, at the versions installed in this checkout's .venv;
#   .gpudata/7scenes-kitchen/
#              the first FRAMES (default 100) 7-Scenes kitchen frames and the intrinsics;
#   .gpudata/room-0-loop/
#              a synthetic room loop of SYNTH_FRAMES (default 60) frames at 320x240, scene
#              seed 0 (bench/odometry.py's first scene), rendered here: the renderer needs
#              open3d, which the GPU machine lacks.
# Both folders are git-ignored (.gitignore, else .git/info/exclude), so they travel only when
# a `run` call names them in `carry`. Refuses when what would travel passes 60 MiB.
#
# Usage: bench/gpu_prepare.sh [--frames N] [--synth-frames N] [--kitchen DIR]
#                             [--python-version 3.12] [--wheels DIR] [--data DIR]
# Example: bench/gpu_prepare.sh --frames 100
set -euo pipefail

REPO=$(cd "$(dirname "$0")/.." && pwd)
cd "$REPO"
FRAMES=100
SYNTH_FRAMES=60
KITCHEN_SRC="$REPO/../shared/data/7scenes-kitchen-0-299"
PYVER=3.12
WHEELS=.whl
DATA=.gpudata
while [ $# -gt 0 ]; do
  case "$1" in
    --frames) FRAMES=$2; shift 2 ;;
    --synth-frames) SYNTH_FRAMES=$2; shift 2 ;;
    --kitchen) KITCHEN_SRC=$2; shift 2 ;;
    --python-version) PYVER=$2; shift 2 ;;
    --wheels) WHEELS=$2; shift 2 ;;
    --data) DATA=$2; shift 2 ;;
    -h|--help) sed -n '2,22p' "$0"; exit 0 ;;
    *) echo "gpu_prepare.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done
PY=${PYTHON:-$REPO/.venv/bin/python}
[ -x "$PY" ] || PY=python3

# What the GPU machine's image lacks among the bench's imports (device KINDS.md lists the
# image's packages: torch, numpy, scipy, opencv-python-headless, pyyaml, rich, typer,
# msgpack are there; zenoh, gtsam and open3d are not and the odometry path never imports
# them). typing-extensions is there too, but pydantic-core needs a recent one: carried.
PACKAGES="pydantic pydantic-core annotated-types typing-inspection typing-extensions"

# Pin each to this checkout's version so that the GPU runs the code the tests ran here.
PINS=$("$PY" - $PACKAGES <<'EOF'
import sys
from importlib.metadata import PackageNotFoundError, version

pins = []
for name in sys.argv[1:]:
    try:
        pins.append(f"{name}=={version(name)}")
    except PackageNotFoundError:
        sys.exit(f"gpu_prepare.sh: {name} is not installed in {sys.executable}; "
                 "install the project first (pip install -e .)")
print(" ".join(pins))
EOF
)
echo "wheels for CPython $PYVER: $PINS"
rm -rf "$WHEELS"
mkdir -p "$WHEELS"
PLATFORMS=""
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 \
         manylinux2014_x86_64 manylinux1_x86_64; do
  PLATFORMS="$PLATFORMS --platform $p"
done
# shellcheck disable=SC2086
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version "$PYVER" \
  --implementation cp $PLATFORMS -d "$WHEELS" $PINS
echo "downloaded:"
ls -1 "$WHEELS"

# Each wheel's own needs must be carried or already on the GPU machine.
"$PY" - "$WHEELS" <<'EOF'
import re
import sys
import zipfile
from pathlib import Path

carried = set()
needs = {}
for wheel in Path(sys.argv[1]).glob("*.whl"):
    with zipfile.ZipFile(wheel) as zf:
        meta = next(n for n in zf.namelist() if n.endswith(".dist-info/METADATA"))
        text = zf.read(meta).decode()
    name = re.search(r"^Name: (.+)$", text, re.M).group(1).strip()
    carried.add(re.sub(r"[-_.]+", "-", name).lower())
    needs[name] = [line.split(":", 1)[1].strip() for line in text.splitlines()
                   if line.startswith("Requires-Dist:") and "extra ==" not in line]
missing = set()
for name, reqs in sorted(needs.items()):
    for req in reqs:
        dep = re.sub(r"[-_.]+", "-", re.match(r"[A-Za-z0-9_.-]+", req).group(0)).lower()
        if dep not in carried:
            missing.add(f"{name} needs {req}")
if missing:
    sys.exit("gpu_prepare.sh: needed but not carried: " + "; ".join(sorted(missing)))
print(f"{len(carried)} wheels, their needs all carried")
EOF

# The kitchen frames: the first FRAMES of each file kind, and the intrinsics.
if [ -d "$KITCHEN_SRC" ]; then
  dest="$DATA/7scenes-kitchen"
  rm -rf "$dest"
  mkdir -p "$dest"
  cp "$KITCHEN_SRC/camera-intrinsics.txt" "$dest/"
  for ((i = 0; i < FRAMES; i++)); do
    stem=$(printf "frame-%06d" "$i")
    if [ ! -f "$KITCHEN_SRC/$stem.color.jpg" ]; then
      echo "gpu_prepare.sh: $KITCHEN_SRC has only $i frames" >&2
      break
    fi
    cp "$KITCHEN_SRC/$stem".* "$dest/"
  done
  echo "copied $(ls "$dest" | grep -c '\.color\.') kitchen frames into $dest"
else
  echo "gpu_prepare.sh: no kitchen frames at $KITCHEN_SRC (--kitchen DIR); the check" \
       "will run the synthetic loop only" >&2
fi

# The synthetic loop, as bench/odometry.py renders its first scene (room, seed 0, loop).
"$PY" -P - "$DATA/room-0-loop" "$SYNTH_FRAMES" <<'EOF'
import logging
import sys
from pathlib import Path

from cpslam.tools.synth import generate

logging.basicConfig(level=logging.WARNING)
generate(Path(sys.argv[1]), scene="room", frames=int(sys.argv[2]), width=320, height=240,
         seed=0, noise=False, loop=True, overwrite=True)
print(f"rendered {sys.argv[2]} synthetic frames into {sys.argv[1]}")
EOF

# Ignored, so that they travel only when carried.
for dir in "$WHEELS" "$DATA"; do
  case "$dir" in /*) continue ;; esac  # outside the checkout: nothing to ignore
  if ! git check-ignore -q "$dir/x"; then
    echo "/${dir#./}/" >> "$(git rev-parse --git-path info/exclude)"
    echo "added /${dir#./}/ to $(git rev-parse --git-path info/exclude)"
  fi
done

# What travels: tracked and untracked-not-ignored files, plus the two carried folders.
"$PY" - "$WHEELS" "$DATA" <<'EOF'
import subprocess
import sys
from pathlib import Path

files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                       capture_output=True, check=True).stdout.split(b"\0")
tree = sum(Path(f.decode()).stat().st_size for f in files if f and Path(f.decode()).is_file())
carried = sum(p.stat().st_size for d in sys.argv[1:] for p in Path(d).rglob("*") if p.is_file())
mib = (tree + carried) / 2**20
print(f"would travel: {tree / 2**20:.1f} MiB of checkout + {carried / 2**20:.1f} MiB carried "
      f"= {mib:.1f} MiB (limit 64 MiB)")
if mib > 60:
    sys.exit("gpu_prepare.sh: over 60 MiB; copy fewer frames (--frames)")
EOF
echo "ready: run bench/gpu_check.sh on the GPU machine with carry [\"$WHEELS\", \"$DATA\"]"
