#!/usr/bin/env bash
# Train a shape prior on a GPU machine that has Python, torch and numpy but no open3d, trimesh, viser or network,
# and that receives this working tree plus what `--prepare` put in runs/carry/ (pass it as a carried path).
#
#   bash scripts/train_gpu.sh --prepare                 here, once: mesh packs + pure-Python wheels -> runs/carry/
#   bash scripts/train_gpu.sh --smoke OUT               there: CUDA, data, 20 steps, a checkpoint in OUT (< 1 min)
#   bash scripts/train_gpu.sh OUT [MINUTES] [train-prior options, which win over the ones below]
#
# The training run resumes efem_viz/weights/<category>_resume.pt (override with --resume-from), prepares its data on
# the GPU from the carried mesh packs (torch signed distance and ray casting; no open3d), trains in bf16 autocast with
# a batch sized for a large GPU, and writes into OUT every minute: last.pt (the full checkpoint), <category>_resume.pt
# (the shippable resume state), <category>.pt (the best export) and the training report (the data cache stays in
# $TMPDIR). The category's own settings are those its CPU runs use (efem_viz/weights/<category>_training_notes.md);
# the weights are averaged as they go (--ema-decay 0.999), and the export is the better of the average and the
# trained weights.
# MINUTES (default 8) is the whole process's budget, data preparation included, so that a call of the device tool
# (9-10 minutes) ends with everything in OUT. Work is counted in iterations (--steps N stops after N of them).
#
# Environment: EFEM_CATEGORY (mug, kitchen or chair; default mug), EFEM_TRAIN_DEVICE (default cuda; cpu runs the
# same path here), EFEM_TRAIN_BATCH (default 256), EFEM_TRAIN_THREADS (default 8), EFEM_CARRY (default runs/carry).
set -euo pipefail
HERE=$PWD  # a relative OUT is where the caller stands
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
CARRY=${EFEM_CARRY:-runs/carry}
WHEELS=(tyro docstring-parser typeguard typing-extensions tqdm)
CAT=${EFEM_CATEGORY:-mug}
case $CAT in  # each prior's own training settings (its training notes)
  mug) CAT_OPTS=(--preset cpu --lr 3e-5); N_VAL=96 ;;
  kitchen) CAT_OPTS=(--preset cpu --lr 1e-4 --top-only-p 0.1 --table-side-p 0.5); N_VAL=96 ;;
  chair) CAT_OPTS=(--preset cpu-chair --lr 3e-4 --top-only-p 0.25 --table-side-p 0.5); N_VAL=48 ;;
  *) echo "[train_gpu] EFEM_CATEGORY must be mug, kitchen or chair, not '$CAT'" >&2; exit 2 ;;
esac

if [[ ${1:-} == --prepare ]]; then
  mkdir -p "$CARRY/wheels"
  $PY -m efem_viz.cli pack-meshes --category "$CAT" --split train --count 400 --out "$CARRY/${CAT}_train.npz"
  $PY -m efem_viz.cli pack-meshes --category "$CAT" --split val --count "$N_VAL" --out "$CARRY/${CAT}_val.npz"
  # pure-Python wheels for a machine without tyro/tqdm (installed there into a temporary folder, never from a network)
  $PY -m pip download -q --only-binary=:all: --no-deps --python-version 3.12 --implementation py \
    --platform any -d "$CARRY/wheels" "${WHEELS[@]}"
  du -sh "$CARRY"
  exit 0
fi

SMOKE=0
if [[ ${1:-} == --smoke ]]; then SMOKE=1; shift; fi
OUT=${1:?usage: bash scripts/train_gpu.sh [--prepare | --smoke OUT | OUT [MINUTES] [train-prior options]]}
shift
MINUTES=8
if (( ! SMOKE )) && [[ $# -gt 0 && $1 != --* ]]; then MINUTES=$1; shift; fi
[[ $OUT == /* ]] || OUT=$HERE/$OUT
DEVICE=${EFEM_TRAIN_DEVICE:-cuda}
mkdir -p "$OUT"
for f in "$CARRY/${CAT}_train.npz" "$CARRY/${CAT}_val.npz"; do
  [[ -f $f ]] || { echo "[train_gpu] missing $f: run 'EFEM_CATEGORY=$CAT bash scripts/train_gpu.sh --prepare' here and carry $CARRY" >&2; exit 1; }
done

# what the machine lacks of the pure-Python dependencies comes from the carried wheels, into a folder of OUT's
if ! $PY -c "import tyro, tqdm" >/dev/null 2>&1; then
  SITE=$(mktemp -d)
  $PY -m pip install -q --no-index --find-links "$CARRY/wheels" --target "$SITE" "${WHEELS[@]}" >&2
  export PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"

$PY - "$DEVICE" <<'PYCHECK' >&2
import sys
import torch
dev = sys.argv[1]
if dev.startswith("cuda") and not torch.cuda.is_available():
    sys.exit("[train_gpu] no CUDA device visible to torch " + torch.__version__ + " (EFEM_TRAIN_DEVICE=cpu runs on the CPU)")
name = torch.cuda.get_device_name(0) if dev.startswith("cuda") else "cpu"
print(f"[train_gpu] torch {torch.__version__} on {name}; python {sys.version.split()[0]}")
PYCHECK

DTYPE=bfloat16
if [[ $DEVICE == cpu ]]; then
  DTYPE=$($PY -c "from efem_viz.prior.config import fast_cpu_bf16; print('bfloat16' if fast_cpu_bf16() else 'float32')")
fi
RESUME=efem_viz/weights/${CAT}_resume.pt
COMMON=(--category "$CAT" "${CAT_OPTS[@]}" --meshes "$CARRY/${CAT}_train.npz" --val-meshes "$CARRY/${CAT}_val.npz"
  --device "$DEVICE" --matmul-dtype "$DTYPE" --threads "${EFEM_TRAIN_THREADS:-8}" --min-views 1
  --sensor-p 0.75 --fixed-point-p 0.25 --decay-at 0.95 --iterations 200000
  --cache-dir "${TMPDIR:-/tmp}/efem-train-cache" --out-dir "$OUT" --export "$OUT/${CAT}.pt"
  --resume-export "$OUT/${CAT}_resume.pt"
  --ckpt-every-min 1 --resume-export-every-min 1 --no-progress --ema-decay 0.999)
[[ -f $RESUME ]] && COMMON+=(--resume-from "$RESUME" --reset-best)
if (( SMOKE )); then
  exec $PY -m efem_viz.cli train-prior "${COMMON[@]}" --n-train 16 --n-val 4 --batch-size 32 --steps 20 \
    --val-every 10 --log-every 5 --time-budget-min 3 "$@"
fi
exec $PY -m efem_viz.cli train-prior "${COMMON[@]}" --n-train 400 --n-val "$N_VAL" \
  --batch-size "${EFEM_TRAIN_BATCH:-256}" --val-every 250 --log-every 50 \
  --time-budget-min "$MINUTES" "$@"
