#!/usr/bin/env bash
# After the shipped prior (efem_viz/weights/mug.pt) changes, rebuild everything that was computed with it:
#   1. its pose codebook (efem_viz/weights/mug_codebook.npz)
#   2. its output-mask threshold tau_out (metadata of mug.pt), calibrated on six generated synthetic table scenes
#      (z, so3, pile; seeds 0 and 1, regenerated here bit-identically; the bench/em.py test scenes are never used)
#   3. the precomputed EFEM traces of every bundled scene that ships one (sample_scenes/<scene>.efem.npz: seed 0,
#      today's presets: 400 proposals on the synthetic scenes, the real preset's 120 spread ones on the real frames;
#      saved compact, latents in float16; traces replay by re-decoding stored latents, so old traces are wrong with
#      new weights)
#   4. the static demo of syn_tree_0 (static/syn_tree_0/)
# Usage: bash scripts/refresh_prior_outputs.sh [--skip-codebook] [--skip-demo]
# Time on a 2-core CPU: about 1 min (codebook) + 1 min (scenes) + 20-60 s per run (synthetic ones twice) + 1 min (demo).
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
OUT=$(mktemp -d)
trap 'rm -rf "$OUT"' EXIT
mkdir -p "$OUT/cal" "$OUT/runs"
for cfg in z so3 pile; do
  for seed in 0 1; do
    $PY -m efem_viz.cli generate --config $cfg --seed $seed --count 1 --mode tsdf --objects 5 --prefix syn_ \
      --out "$OUT/cal"
  done
done
# tau_out for these weights, chosen on the calibration runs (the masks are re-derived; nothing else re-runs)
$PY -m efem_viz.cli segment "$OUT"/cal/*.ply --prior mug --preset synthetic --proposals 400 --seed 0 \
  --out "$OUT/cal_runs" --no-scannet --no-ply
$PY -m efem_viz.cli calibrate-masks "$OUT/cal_runs" --gt "$OUT"/cal/*.ply --prior mug --write \
  --json-out efem_viz/weights/mug_tau_out.json
# the bundled traces: synthetic scenes with the synthetic preset, real ones with real
SHIPPED=(sample_scenes/*.efem.npz)
SYN=(); REAL=()
for f in "${SHIPPED[@]}"; do
  s=${f%.efem.npz}.ply
  [[ $(basename "$s") == syn_chairs_* ]] && continue  # made with the chair prior (sample_scenes/README.md)
  if [[ $(basename "$s") == real_* ]]; then REAL+=("$s"); else SYN+=("$s"); fi
done
(( ${#SYN[@]} )) && $PY -m efem_viz.cli segment "${SYN[@]}" --prior mug --preset synthetic --proposals 400 \
  --seed 0 --out "$OUT/runs" --no-scannet --no-ply
(( ${#REAL[@]} )) && $PY -m efem_viz.cli segment "${REAL[@]}" --prior mug --preset real \
  --seed 0 --out "$OUT/runs" --no-scannet --no-ply
for f in "$OUT"/runs/*.efem.npz; do
  $PY -c "import sys; from efem_viz.em.results import EMResult; EMResult.load(sys.argv[1]).save(sys.argv[2], compact=True)" \
    "$f" "sample_scenes/$(basename "$f")"
done
$PY -m efem_viz.cli evaluate sample_scenes --gt sample_scenes --no-strict  # real_tabletop_0, _8: no trace
if [[ $SKIP_DEMO == 0 ]]; then
  $PY -m efem_viz.viewer.export sample_scenes/syn_tree_0.ply --prior mug --out static/syn_tree_0
fi
echo "[refresh] done: commit efem_viz/weights/mug.pt (tau_out metadata) mug_codebook.npz mug_tau_out.json" \
  "sample_scenes/*.efem.npz static/syn_tree_0/"
