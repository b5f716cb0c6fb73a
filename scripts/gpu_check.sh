#!/usr/bin/env bash
# Device check on a lent CUDA machine (issues 30 and 33), one command:
#  1. the demo phantom (1 mm) registered as a user would, on CUDA (warm-up, then timed) and on the CPU with the
#     same TTO size: stage times next to the paper's H100 figures, CPU/GPU pose agreement
#     (benchmarks/gpu_compare.py -> $OUT/gpu_check.md);
#  2. `geopose bench` on the default path (CUDA), held-out phantoms in parallel processes, each resuming from
#     its cases/ folder; the finished cases come back in $OUT/bench_cases.tar.gz (merge them here with
#     `geopose bench --out DIR` after unpacking into DIR/cases).
# Usage: scripts/gpu_check.sh [PROCESSES] [SUBJECTS_EACH] [BENCH_SECONDS]
# Wheels the machine lacks travel in .whl/ (SimpleITK as its package plus its library xz-compressed, to fit
# the 64 MiB transfer); the real head headsq in .data/headsq.
set -uo pipefail
procs=${1:-6}; each=${2:-7}; bench_s=${3:-400}
out=${OUT:-out}; mkdir -p "$out"
site=/tmp/site
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target $site .whl/*.whl || exit 1
  tar -xzf .whl/simpleitk_py.tar.gz -C $site
  python3 -c "import lzma, shutil; shutil.copyfileobj(lzma.open('.whl/_SimpleITK.abi3.so.xz'), open('$site/SimpleITK/_SimpleITK.abi3.so', 'wb'))"
fi
export PYTHONPATH=$site:$PWD/Logic PYTHONUNBUFFERED=1
G="python3 -m geopose.cli"
nvidia-smi -L; python3 -c "import torch, SimpleITK, pydicom; print('torch', torch.__version__, torch.cuda.get_device_name(0))"
t0=$(date +%s)
case=/tmp/demo_case
$G phantom --seed 20260 --spacing-mm 1 --out $case > /dev/null || exit 1
reg() { $G register --cta $case/cta.nii.gz --dsa-pa $case/dsa_pa.dcm --dsa-lat $case/dsa_lat.dcm --tto-px 256 "$@" 2>&1 | tr '\r' '\n' | grep -v '\[' ; }
reg --device cuda --out /tmp/warm > /dev/null
reg --device cuda --out /tmp/r_cuda | tail -3
cp /tmp/r_cuda/result.json "$out/demo_cuda.json"
echo "part 1 took $(( $(date +%s) - t0 )) s"
# the CPU registration runs beside the benchmark: its pose is compared, its time is not the laptop's
(OMP_NUM_THREADS=4 reg --device cpu --out /tmp/r_cpu | tail -3; cp /tmp/r_cpu/result.json "$out/demo_cpu.json"
 python3 benchmarks/gpu_compare.py --cuda /tmp/r_cuda/result.json --cpu /tmp/r_cpu/result.json --doc "$out/gpu_check.md") &
threads=$(( $(nproc) / (procs + 1) )); [ $threads -lt 1 ] && threads=1
for p in $(seq 0 $(( procs - 1 ))); do
  start=$(( 5000 + p * each ))
  OMP_NUM_THREADS=$threads timeout "$bench_s" $G bench --subjects $each --seed-start $start --spacing-mm 2 --long-iterations 0 \
    --device cuda --out /tmp/bench_$p > /tmp/bench_$p.log 2>&1 &
done
# one more process: the dense-opacification phantoms and the real head (after its one phantom subject, 5000)
real=""; [ -d .data/headsq ] && real="--headsq .data/headsq/quarter_sidecar.mhd --real-seeds 1 --real-arteries"
OMP_NUM_THREADS=$threads timeout "$bench_s" $G bench --subjects 1 --seed-start 5000 --spacing-mm 2 --long-iterations 0 \
  --device cuda --out /tmp/bench_x --dense all_territories avm late_venous --dense-subjects 1 $real > /tmp/bench_x.log 2>&1 &
wait
tail -n 2 /tmp/bench_*.log
mkdir -p /tmp/merged/cases; cp /tmp/bench_*/cases/*.json /tmp/merged/cases/ 2>/dev/null
ls /tmp/merged/cases | wc -l
tar -czf "$out/bench_cases.tar.gz" -C /tmp/merged cases
echo "total $(( $(date +%s) - t0 )) s"
