#!/usr/bin/env bash
# Sourced by bench/gpu_check.sh, or before any bench script on the GPU machine: installs the
# wheels in $WHEELS (bench/gpu_prepare.sh makes them) into $SITE/lib and lays cpslam out from
# this checkout in $SITE/src, as pyproject.toml's package-dir mapping says (symbolic links; no
# build: setuptools may be too old there and nothing downloads), then exports PYTHONPATH.
# Run python with -P so that the checkout's own cpslam/ folder does not shadow the layout.
#
# Reads (with defaults): WHEELS (.whl), PY (python3), SITE (a new /tmp/cpslam-gpu.* folder).
# Example (the device tool, carry [".whl", ".gpudata"]):
#   source bench/gpu_env.sh && python3 -P bench/gpu_profile.py --data .gpudata/7scenes-kitchen
WHEELS=${WHEELS:-${CPSLAM_GPU_WHEELS:-.whl}}
PY=${PY:-${PYTHON:-python3}}
SITE=${SITE:-$(mktemp -d /tmp/cpslam-gpu.XXXXXX)}
REPO=${REPO:-$(pwd)}
if compgen -G "$WHEELS/*.whl" >/dev/null; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target "$SITE/lib" "$WHEELS"/*.whl || { echo "gpu_env: wheel install failed"; return 1; }
else
  echo "gpu_env: no wheels in $WHEELS; using what $PY has"
fi
"$PY" - "$REPO" "$SITE/src" <<'EOF' || return 1
import sys
import tomllib
from pathlib import Path

repo, dest = Path(sys.argv[1]), Path(sys.argv[2])
mapping = tomllib.loads((repo / "pyproject.toml").read_text())["tool"]["setuptools"]
mapping = mapping["package-dir"]
root = dest / "cpslam"
root.mkdir(parents=True)
for entry in (repo / mapping["cpslam"]).iterdir():
    (root / entry.name).symlink_to(entry)
for package, folder in mapping.items():
    if package != "cpslam":
        root.joinpath(*package.split(".")[1:]).symlink_to(repo / folder)
EOF
export PYTHONPATH="$SITE/src:$SITE/lib${PYTHONPATH:+:$PYTHONPATH}"
