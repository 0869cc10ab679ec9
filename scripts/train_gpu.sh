#!/usr/bin/env bash
# One command that continues the mug prior on a GPU for a fixed number of minutes (issue 34 item 4): it resumes
# from a resume state (default: the committed efem_viz/weights/mug_256x4_resume.pt, the 256-wide decoder grown from
# the shipped prior in session 11), trains in bf16 with a batch sized
# for a large GPU, and writes checkpoints (last.pt every 2 min, snapshots every 500 iterations), the best export
# (OUT/mug.pt), a resume state (OUT/mug_resume.pt) and the training report into OUT.
#
#   bash scripts/train_gpu.sh OUT [MINUTES] [more train-prior options, which win over the ones below]
#   e.g. bash scripts/train_gpu.sh "$OUT" 7 --resume-from runs/cap_256x4/last.pt
#
# MINUTES (default 7) is the whole process's budget, data preparation included (about 3 min for a fresh data cache
# of the 496 procedural mugs on one core), so that the command ends under the device tool's 9-minute limit.
# EFEM_TRAIN_DEVICE (default cuda), EFEM_TRAIN_BATCH (default 128), EFEM_TRAIN_THREADS (default 8) change the
# device, the batch and the CPU threads. On a CPU the matrix work stays float32 (bf16 is fast only on AMX /
# AVX-512 BF16 CPUs and GPUs; `efem_viz.prior.config.fast_cpu_bf16`).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:?usage: bash scripts/train_gpu.sh OUT_DIR [MINUTES] [train-prior options]}
MINUTES=${2:-7}
shift $(( $# >= 2 ? 2 : 1 ))
DEVICE=${EFEM_TRAIN_DEVICE:-cuda}
DTYPE=bfloat16
if [[ $DEVICE == cpu ]]; then
  DTYPE=$(python3 -c "from efem_viz.prior.config import fast_cpu_bf16; print('bfloat16' if fast_cpu_bf16() else 'float32')")
fi
mkdir -p "$OUT"
exec python3 -m efem_viz.cli train-prior --category mug --preset cpu --n-train 400 --n-val 96 \
  --batch-size "${EFEM_TRAIN_BATCH:-128}" --iterations 60000 --lr 3e-5 --decay-at 0.95 --val-every 250 \
  --ckpt-every-min 2 --resume-export-every-min 2 --threads "${EFEM_TRAIN_THREADS:-8}" --min-views 1 \
  --sensor-p 0.75 --fixed-point-p 0.25 --snapshot-every 500 --device "$DEVICE" --matmul-dtype "$DTYPE" \
  --resume-from efem_viz/weights/mug_256x4_resume.pt --reset-best \
  --out-dir "$OUT" --export "$OUT/mug.pt" --resume-export "$OUT/mug_resume.pt" \
  --time-budget-min "$MINUTES" --no-progress "$@"
