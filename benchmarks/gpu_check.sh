#!/usr/bin/env bash
# The GPU checks of the SfM pipeline and of training, sized for one H100 with 16 cores: at most
# 330 s (the steps' budgets), about 4 minutes expected, the machine's start-up excluded
# (docs/performance.md, "On a GPU: the prepared scripts").
#   bash benchmarks/gpu_check.sh              # on the GPU machine; figures also in $OUT/gpu_check.txt
#   bash benchmarks/gpu_check.sh --rehearse   # the same steps at a tiny size on the CPU (tests/whole/test_gpu_scripts.py)
# A GPU machine without a package index: run here, once, from the project's root,
#   GPU_EXTRA_PACKAGES="nh3 loky" bash ../shared/tools/gpu/bundle.sh
# (nh3: report.html's sanitizer, a runtime dependency the bundle's list predates; the machine's image
# has threadpoolctl, numba, tabulate, markdown, jinja2, h5py, timm, tensorboard), copy the git-ignored
# .gpu/ along with the checkout, and there: source .gpu/env.sh && bash benchmarks/gpu_check.sh
# Steps, each under its own `timeout` of its budget:
# 1. (45 s) the CUDA tests (GPU matches equal the CPU's, ties included; the GPU pipeline stores what the
#    CPU workers store; DenseVLAD on the GPU equals the CPU's); rehearsed: collected only;
# 2. (60 s) bench_matching.py at 5,000 and 20,000 keypoints: the pipeline beside the naive float16/float32
#    torch matchers and the bare product, measured in the same run on the same device;
# 3. (120 s) bench_scale.py --size baidu: unit costs at 20,000 keypoints, the projected full sweep,
#    a slice of 0.5 % of the queries (its default on a GPU is 2 %) forecast, then run end to end;
# 4. (55 s) bench_training.py: train.py's loop against the bare step on the GPU, and the data pipeline alone;
# 5. (50 s) the README's evaluation (the built-in scene, `python evaluate.py`) with its SfM on the GPU.
# The built-in scene is rendered on the CPU's cores (the scene of docs/results.md), into the cache
# that gpu_training_gain.sh reuses on the same machine.
set -uo pipefail
source "$(dirname "$0")/gpu_steps.sh" gpu_check.txt "$@"

set -f  # the overrides' brackets are no file patterns
if [ "$REHEARSE" = 1 ]; then
    # a tiny scene: 24 database images and 6 queries of 160 x 120, rendered by a pool as on the GPU machine
    scene="data.render.device=cpu data.render.workers=$(nproc) data.render.width=160 data.render.height=120
        data.render.num_database=24 data.render.num_queries=6 data.render.texture_size=64 data.render.length=20"
    collect_only="--collect-only"
    matching="--keypoints 300 600 --repeats 1 --pipeline-images 3"
    scale="--scale 0.05 --dimension 256 --keypoints 1000 --slice-keypoints 300"
    training="--steps 4 --overrides datamodule.image_size=[96,72] sampler.anchors=3 sampler.negatives=2"
    # a coarser DenseVLAD (a vocabulary of 20,000 RootSIFTs in 10 iterations), 100 bootstrap resamples
    densevlad="model.step=4 model.vocabulary_samples=20000 model.kmeans_iterations=10 metrics.uncertainty.resamples=100"
else
    scene="data.render.device=cpu data.render.workers=$(nproc)"  # the built-in scene, on every core
    collect_only="" matching="--keypoints 5000 20000 --repeats 5" scale="--slice 0.005"
    training="--steps 20 --overrides" densevlad=""
fi

require_gpu
versions
step "CUDA tests" 45 "$PYTHON" -m pytest -q -p no:cacheprovider $collect_only \
    tests/sfm/test_nearest_neighbours.py tests/sfm/test_matching.py tests/models/published/test_densevlad.py -k "gpu or cuda or device"
step "bench_matching" 60 "$PYTHON" benchmarks/bench_matching.py $matching
step "bench_scale baidu" 120 "$PYTHON" benchmarks/bench_scale.py --size baidu $scale
step "bench_training" 55 "$PYTHON" benchmarks/bench_training.py $training device=$DEVICE $scene
step "evaluate the built-in scene, SfM on the GPU" 50 "$PYTHON" evaluate.py device=$DEVICE $scene $densevlad \
    paths.root_dir="$WORK" hydra.run.dir="$WORK/evaluate" report.figure_formats=[] \
    report.scene_view.enabled=false output.ltvl=false
finish
