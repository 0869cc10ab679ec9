#!/usr/bin/env bash
# EFEM's GPU path checked against the CPU on a GPU machine that has Python, torch, numpy, scipy and scikit-image but
# no open3d, trimesh, pybullet, viser or network, and that receives this working tree plus what `--prepare` put in
# runs/carry/gpu_check/ (pass it as a carried path).
#
#   bash scripts/gpu_check.sh --prepare            here, once: the synthetic scene z_7000 + pure-Python wheels
#   bash scripts/gpu_check.sh OUT [options]        there: python -m bench.gpu_check, its JSON and log into OUT
#
# The options go to bench/gpu_check.py (default: the three bundled real frames and z_7000, CPU once, GPU twice; about
# 3 minutes of CPU solves on a 16-core machine). Environment: EFEM_CARRY (default runs/carry), EFEM_CHECK_DEVICE
# (default cuda; cpu runs the same comparison here).
set -euo pipefail
HERE=$PWD  # a relative OUT is where the caller stands
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
CARRY=${EFEM_CARRY:-runs/carry}/gpu_check
WHEELS=(trimesh plyfile)

if [[ ${1:-} == --prepare ]]; then
  mkdir -p "$CARRY/wheels"
  PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" $PY - "$CARRY" <<'PYPREP'
import sys
from pathlib import Path

from bench.em import get_scene
from efem_viz.data.io import save_scene

out = Path(sys.argv[1]) / "z_7000.npz"
save_scene(get_scene("z", 7000, "points"), out)
print(f"[gpu_check] wrote {out}")
PYPREP
  # pure-Python wheels of the versions installed here (installed there into a temporary folder, never from a network)
  specs=()
  for w in "${WHEELS[@]}"; do specs+=("$w==$($PY -c "import importlib.metadata as m; print(m.version('$w'))")"); done
  $PY -m pip download -q --only-binary=:all: --no-deps --python-version 3.12 --implementation py \
    --platform any -d "$CARRY/wheels" "${specs[@]}"
  du -sh "$CARRY"
  exit 0
fi

OUT=${1:?usage: bash scripts/gpu_check.sh [--prepare | OUT [bench.gpu_check options]]}
shift
[[ $OUT == /* ]] || OUT=$HERE/$OUT
[[ -f $CARRY/z_7000.npz ]] || { echo "[gpu_check] missing $CARRY/z_7000.npz: run 'bash scripts/gpu_check.sh --prepare' here and carry ${CARRY%/gpu_check}" >&2; exit 1; }
mkdir -p "$OUT"
if ! $PY -c "import trimesh, plyfile" >/dev/null 2>&1; then
  SITE=$(mktemp -d)
  $PY -m pip install -q --no-index --no-deps --find-links "$CARRY/wheels" --target "$SITE" "${WHEELS[@]}" >&2  # numpy is there
  export PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
set -o pipefail
$PY -m bench.gpu_check --device "${EFEM_CHECK_DEVICE:-cuda}" --scene-dir "$CARRY" --out "$OUT/gpu_check.json" "$@" \
  2>&1 | tee "$OUT/gpu_check.log"
