#!/usr/bin/env bash
# The prepared GPU check of issue 41, run from the repository root on a lent GPU machine (device `run`, with
# `.whl` carried: the wheels of the dependencies that machine's image lacks, see the device README):
#   the simulator's and the relight footprints' CUDA tests, `sss bench sim` (1080p render on the GPU against numpy), and
#   `sss repro paper --budget BUDGET` (Tables 1-2 at the paper's scale); reports land in $OUT.
# The wheels (here, once; `.whl/` is ignored by git): for each of pyzmq==27.3.0 kornia==0.9.0 kornia_rs==0.2.0
#   colour-demosaicing==0.2.7 colour-science==0.4.7 donfig==0.8.1.post1 google-crc32c==1.9.0 numcodecs==0.16.6
#   zarr==3.1.6 OpenEXR==3.5.3 tomli_w==1.2.0:  python3 -m pip download --no-deps --only-binary=:all:
#   --python-version 3.12 --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64
#   --platform manylinux2014_x86_64 --platform manylinux_2_26_x86_64 -d .whl NAME==VERSION   (31 MB in all)
# Usage: benchmarks/device/paper.sh [BUDGET_S] [repro|all]   (repro first, then the tests and `sss bench sim`;
#   "repro": the repro alone). One call: timeout_s = BUDGET_S + about 150 (install ~20 s; the repro's own deadline
#   is BUDGET_S + 110, so that its report comes back). Next lent GPU: `paper.sh 330 repro`, timeout_s 480 (one call
#   within the issue's 8 minutes: 338 s on an H100 on 2026-12-05); then at once, while the machine is warm (it keeps
#   /tmp/repro for about 30 s): `paper.sh 250 repro`, timeout_s 390, which skips the finished steps and relights
#   what is left (each relight is kept as it finishes; on 2026-12-05 it relit the crab with the decoder in 113 s,
#   and a third call got no answer from the machine).
set -o pipefail
budget=${1:-300}
out=${OUT:-/tmp/out}
mkdir -p "$out"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index . || exit 1
nvidia-smi -L
# its own deadline (the report is rewritten after every step), so that what it wrote comes back even if it overruns
timeout -k 10 -s INT $((budget + 110)) python3 -m sssphase_cli repro paper --device cuda --budget "$budget" --out /tmp/repro 2>&1 \
  | grep -v "━" | tail -80
cp /tmp/repro/report.md /tmp/repro/report.json "$out/" 2>/dev/null
for d in /tmp/repro/runs/*/; do cp "$d/metrics.jsonl" "$out/$(basename "$d")_metrics.jsonl" 2>/dev/null; done
if [ "$2" != repro ]; then
  python3 -m pytest -q -p no:cacheprovider -o addopts="" tests/sim/test_sim_accel.py 2>&1 | tail -3
  # the footprints a GPU relight keeps on the device: the analytic render, the decoder's guard and tail (CUDA tests)
  python3 -m pytest -q -p no:cacheprovider -o addopts="" -k "device or gpu" tests/learn/test_learn_backends.py \
    tests/learn/test_learn_domain.py 2>&1 | tail -3
  timeout -k 5 -s INT "${SIM_S:-300}" python3 -m sssphase_cli bench sim --device cuda --out "$out/sim.json" 2>&1 | tail -20
fi
ls -la "$out"
