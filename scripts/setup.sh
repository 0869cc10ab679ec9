#!/usr/bin/env bash
# Installs everything efem-viz needs on a fresh Debian machine (idempotent; fast when already installed).
#   bash scripts/setup.sh          runtime: system libraries for open3d, CPU torch, efem-viz (editable)
#   bash scripts/setup.sh --test   also the test extras and Debian chromium for the real-browser tests
set -euo pipefail
cd "$(dirname "$0")/.."
WITH_TEST=0
[[ "${1:-}" == "--test" ]] && WITH_TEST=1

SUDO=""
if [[ "$(id -u)" != "0" ]] && command -v sudo >/dev/null 2>&1; then SUDO="sudo"; fi

# System packages: open3d needs libusb/libGL/libgomp; browser tests need Debian's chromium (never `playwright install`).
# g++ builds the fused VN encoder kernels once per machine (without it the encoder runs eagerly, slower).
PKGS=(libusb-1.0-0 libgl1 libgomp1 g++)
[[ $WITH_TEST == 1 ]] && PKGS+=(chromium)
missing=()
for p in "${PKGS[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
if (( ${#missing[@]} )); then
  echo "[setup] apt-get install ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
# CPU torch: 2.13.0 comes from the local wheel on these machines; a bare `torch` would pull a multi-GB CUDA build.
if ! $PY -c "import torch" >/dev/null 2>&1; then
  echo "[setup] pip install torch==2.13.0 (CPU build)"
  $PY -m pip install -q torch==2.13.0
fi
EXTRA=""
[[ $WITH_TEST == 1 ]] && EXTRA="[test,ray]"  # ray: tests/test_batch.py runs the Ray backend (fails, never skips, without it)
echo "[setup] pip install -e .${EXTRA}"
$PY -m pip install -q -e ".${EXTRA}" 2>&1 | grep -v -E "Running pip as the 'root' user|notice" || true
# the check runs from another folder: from the checkout, `import efem_viz` would succeed without any install
HERE=$PWD
(cd / && $PY -c "import efem_viz, annotator, torch, open3d, viser, sys; \
  assert efem_viz.__file__.startswith(sys.argv[1]), efem_viz.__file__" "$HERE") \
  || { echo "[setup] install check failed: efem_viz does not import from outside the checkout" >&2; exit 1; }
command -v efem-viz >/dev/null || { echo "[setup] install check failed: no efem-viz command on PATH" >&2; exit 1; }
echo "[setup] ok"
