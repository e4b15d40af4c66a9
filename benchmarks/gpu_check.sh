#!/usr/bin/env bash
# The GPU checks of the SfM pipeline, sized for one H100 in at most 8 minutes (docs/performance.md):
#   source .gpu/env.sh && bash benchmarks/gpu_check.sh        (on the GPU machine; DEVELOPERS: docs/development.md)
# 1. the CUDA tests (GPU matches equal the CPU's, ties included; the GPU pipeline stores what the CPU stores);
# 2. bench_matching.py at 5,000 and 20,000 keypoints: the pipeline beside the naive float16/float32 torch
#    matchers and the bare product, measured in the same run on the same device;
# 3. bench_scale.py --size baidu: unit costs, the projected full sweep, a 2 % slice forecast then run;
# 4. a small end-to-end evaluation (the built-in scene) with its SfM on the GPU.
# Figures go to stdout and, when $OUT is set, to $OUT/gpu_check.txt.
set -uo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
log=${OUT:-/tmp}/gpu_check.txt
: > "$log"
status=0
step() {
    echo "== $1" | tee -a "$log"
    shift
    local started=$SECONDS
    "$@" 2>&1 | tee -a "$log"
    local code=${PIPESTATUS[0]}
    echo "== exit $code in $((SECONDS - started)) s" | tee -a "$log"
    [ "$code" -eq 0 ] || status=1
}
step "CUDA tests" timeout 120 "$PYTHON" -m pytest -q -p no:cacheprovider tests/test_features_matching.py tests/test_densevlad.py -k "gpu or cuda or device"
step "bench_matching" timeout 90 "$PYTHON" benchmarks/bench_matching.py --keypoints 5000 20000 --repeats 5
step "bench_scale baidu" timeout 300 "$PYTHON" benchmarks/bench_scale.py --size baidu
step "evaluate on the GPU (built-in scene, 16 queries)" timeout 90 "$PYTHON" evaluate.py device=cuda paths.root_dir=/tmp/gpu_check \
    data.render.num_database=48 data.render.num_queries=16 report.figure_formats=[] report.scene_view.enabled=false output.ltvl=false
exit $status
