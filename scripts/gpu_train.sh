#!/usr/bin/env bash
# Train the shipped networks on a lent CUDA machine (see docs/training.md).
# Usage: scripts/gpu_train.sh init|refine   (results are copied to $OUT when set)
# Both stages train on the inference look and clip (docs/training.md sections 7-8).
# Wheels missing on the machine (SimpleITK, pydicom) may be carried in .whl/.
set -euo pipefail
stage=${1:?init or refine}
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site:$PWD/Logic
else
  export PYTHONPATH=$PWD/Logic
fi
export PYTHONUNBUFFERED=1
G="python3 -m geopose.cli"
OUTDIR=${OUT:-out/results}
mkdir -p out "$OUTDIR"
nvidia-smi -L || true
[ -f out/pop.pt ] || $G train population --phantoms 100-147 --spacing 2 --workers 14 --out out/pop.pt
[ -f out/val.pt ] || $G train population --phantoms 900-907 --spacing 2 --workers 8 --out out/val.pt
case "$stage" in
  init)
    $G train init --population out/pop.pt --out out/runs/init --steps 3000 --max-minutes "${MINUTES:-5}" \
      --batch-size 32 --accumulation 1 --lr 5e-4 --width 48 --dsa-look-p 0.5 --input-clip 2 98 --seed 1
    cp out/runs/init/init.pt out/runs/init/log.csv "$OUTDIR/" ;;
  refine)
    $G train refine --population out/pop.pt --out out/runs/refine --init-model out/runs/init/init.pt --steps 3000 \
      --max-minutes "${MINUTES:-5}" --batch-size 32 --accumulation 1 --lr 5e-4 --width 48 --seed 2 \
      --calibration-samples 0 --dsa-look-p 0.5 --input-clip 2 98
    $G train evaluate --population out/val.pt --init out/runs/init/init.pt --refine out/runs/refine/refine.pt \
      --samples 192 --out "$OUTDIR/metrics.json"
    cp out/runs/refine/refine.pt out/runs/refine/log.csv "$OUTDIR/" ;;
  *) echo "unknown stage $stage" >&2; exit 2 ;;
esac
