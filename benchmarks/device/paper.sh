#!/usr/bin/env bash
# The prepared GPU check of issue 41, run from the repository root on a lent GPU machine (device `run`, with
# `.whl` carried: the wheels of the dependencies that machine's image lacks, see the device README):
#   the simulator's CUDA tests, `sss bench sim` (1080p render on the GPU against numpy), and
#   `sss repro paper --budget BUDGET` (Tables 1-2 at the paper's scale); reports land in $OUT.
# Usage: benchmarks/device/paper.sh [BUDGET_S] [repro]   ("repro": the repro alone)
set -o pipefail
budget=${1:-300}
out=${OUT:-/tmp/out}
mkdir -p "$out"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index . || exit 1
nvidia-smi -L
if [ "$2" != repro ]; then
  python3 -m pytest -q -p no:cacheprovider -o addopts="" tests/sim/test_sim_accel.py 2>&1 | tail -3
  python3 -m sssphase_cli bench sim --device cuda --out "$out/sim.json" 2>&1 | tail -20
fi
python3 -m sssphase_cli repro paper --device cuda --budget "$budget" --out /tmp/repro 2>&1 | grep -v "━" | tail -80
cp /tmp/repro/report.md /tmp/repro/report.json "$out/" 2>/dev/null
for d in /tmp/repro/runs/*/; do cp "$d/metrics.jsonl" "$out/$(basename "$d")_metrics.jsonl" 2>/dev/null; done
ls -la "$out"
