#!/usr/bin/env bash
# After the shipped prior (efem_viz/weights/mug.pt) changes, rebuild everything that was computed with it:
#   1. its pose codebook (efem_viz/weights/mug_codebook.npz)
#   2. its output-mask threshold tau_out (metadata of mug.pt), calibrated on the 6 synthetic sample scenes
#      (`efem-viz calibrate-masks`; the bench/em.py test scenes are never used for it)
#   3. the precomputed EFEM traces of every bundled scene (sample_scenes/<scene>.efem.npz; traces replay by
#      re-decoding stored latents, so old traces are wrong with new weights)
#   4. the static demos of syn_z_0 and syn_tree_0 (static/syn_z_0/, static/syn_tree_0/)
# Usage: bash scripts/refresh_prior_outputs.sh [--skip-codebook] [--skip-demo]
# Time on a 2-core CPU: about 1 min (codebook) + 10-30 s per scene (synthetic ones twice) + 1 min (demo).
set -euo pipefail
cd "$(dirname "$0")/.."
SKIP_CB=0; SKIP_DEMO=0
for a in "$@"; do
  case "$a" in
    --skip-codebook) SKIP_CB=1 ;;
    --skip-demo) SKIP_DEMO=1 ;;
    *) echo "unknown option $a" >&2; exit 2 ;;
  esac
done
PY=${PYTHON:-python3}
if [[ $SKIP_CB == 0 ]]; then
  $PY -m efem_viz.cli build-codebook --prior mug --count 150 --n-store 2000 --noise 0.01 --seed 0
fi
# The bundled traces: 100 proposals, seed 0; synthetic scenes with the synthetic preset, real ones with
# real (efem-method.md §3.12; the demo config equals the real-mugs config).
OUT=$(mktemp -d)
trap 'rm -rf "$OUT"' EXIT
# tau_out is calibrated on the six table scenes (z, so3, pile) as it always was; the arrangement scenes (tree, box,
# shelf) only get their traces
CAL=(sample_scenes/syn_z_*.ply sample_scenes/syn_so3_*.ply sample_scenes/syn_pile_*.ply)
$PY -m efem_viz.cli segment "${CAL[@]}" --prior mug --preset synthetic --proposals 100 --seed 0 \
  --out "$OUT" --no-scannet --no-ply
# tau_out for these weights, chosen on the synthetic runs just made; then the runs again with it (the masks and
# the recorded config change, nothing else)
$PY -m efem_viz.cli calibrate-masks "$OUT" --gt "${CAL[@]}" --prior mug --write \
  --json-out efem_viz/weights/mug_tau_out.json
$PY -m efem_viz.cli segment sample_scenes/syn_*.ply --prior mug --preset synthetic --proposals 100 --seed 0 \
  --out "$OUT" --no-scannet --no-ply
$PY -m efem_viz.cli segment sample_scenes/real_tabletop_*.ply --prior mug --preset real --proposals 100 \
  --seed 0 --out "$OUT" --no-scannet --no-ply
cp "$OUT"/*.efem.npz sample_scenes/
$PY -m efem_viz.cli evaluate sample_scenes --gt sample_scenes
if [[ $SKIP_DEMO == 0 ]]; then
  $PY -m efem_viz.viewer.export sample_scenes/syn_z_0.ply --prior mug
  $PY -m efem_viz.viewer.export sample_scenes/syn_tree_0.ply --prior mug
fi
echo "[refresh] done: commit efem_viz/weights/mug.pt (tau_out metadata) mug_codebook.npz mug_tau_out.json" \
  "sample_scenes/*.efem.npz static/syn_z_0/ static/syn_tree_0/"
