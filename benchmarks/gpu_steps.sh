# The step runner of the prepared GPU scripts (gpu_check.sh, gpu_training_gain.sh), sourced by them:
#   source benchmarks/gpu_steps.sh <log name> "$@"
# Arguments: --rehearse (or REHEARSE=1 in the environment): the same steps at a tiny size on the CPU
# (CUDA hidden), each step's time limit raised to REHEARSAL_LIMIT seconds (a loaded CPU is no GPU).
# Environment: OUT (where the log goes, default /tmp), WORK (scratch: runs and, unless
# LOCRETRIEVAL_CACHE is set, the cache, shared by both scripts; default /tmp/locretrieval_gpu),
# PYTHON (default python3).
# `step NAME BUDGET COMMAND...` runs COMMAND under `timeout BUDGET` (seconds of the GPU machine),
# its output to stdout, the log and, when STEP_COPY names a file, that file; then its exit status
# and time against the budget. `finish` prints every step's line and the total, and exits 1 when a
# step failed.

REHEARSE=${REHEARSE:-0}
REHEARSAL_LIMIT=${REHEARSAL_LIMIT:-600}
log_name=$1
shift
for argument in "$@"; do
    case $argument in
        --rehearse) REHEARSE=1 ;;
        *) echo "unknown argument: $argument (only --rehearse)" >&2; exit 2 ;;
    esac
done
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PYTHON=${PYTHON:-python3}
OUT=${OUT:-/tmp}
WORK=${WORK:-/tmp/locretrieval_gpu}
mkdir -p "$OUT" "$WORK"
export LOCRETRIEVAL_CACHE=${LOCRETRIEVAL_CACHE:-$WORK/cache}
export PYTHONUNBUFFERED=1 MPLBACKEND=Agg
log=$OUT/$log_name
: > "$log"
status=0
steps=()
budgets=0
started_all=$SECONDS
if [ "$REHEARSE" = 1 ]; then
    export CUDA_VISIBLE_DEVICES=""  # every device: auto resolves to the CPU
    DEVICE=cpu
else
    DEVICE=cuda
fi

say() {
    echo "$*" | tee -a "$log"
}

step() {
    local name=$1 budget=$2
    shift 2
    local limit=$budget
    [ "$REHEARSE" = 1 ] && limit=$REHEARSAL_LIMIT
    budgets=$((budgets + budget))
    say "== $name (budget $budget s on the GPU machine)"
    local started=$SECONDS
    [ -z "${STEP_COPY:-}" ] || : > "$STEP_COPY"
    timeout -k 10 "$limit" "$@" 2>&1 | tee -a "$log" "${STEP_COPY:-/dev/null}"
    local code=${PIPESTATUS[0]} used=$((SECONDS - started))
    local verdict="ok"
    [ "$code" -eq 0 ] || { verdict="FAILED (exit $code$([ "$code" -eq 124 ] && echo ", out of time"))"; status=1; }
    [ "$REHEARSE" = 1 ] || [ "$used" -le "$budget" ] || verdict="$verdict, over budget"
    steps+=("$(printf '%-46s %4d s of %4d s  %s' "$name" "$used" "$budget" "$verdict")")
    say "== $name: exit $code in $used s of $budget s"
}

# Refuse a GPU run without a GPU: its figures would be the CPU's.
require_gpu() {
    [ "$REHEARSE" = 1 ] && return 0
    "$PYTHON" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" || {
        say "no CUDA GPU visible to torch: run this on a GPU machine, or rehearse it with --rehearse"
        exit 1
    }
}

# The versions the figures depend on, and the machine.
versions() {
    say "== $(date -u +%FT%TZ) $(uname -m), $(nproc) cores$([ "$REHEARSE" = 1 ] && echo ", REHEARSAL on the CPU")"
    "$PYTHON" - <<'PY' 2>&1 | tee -a "$log"
import importlib.metadata as metadata
import torch
device = torch.cuda.get_device_name() if torch.cuda.is_available() else "no CUDA GPU"
packages = ("torch", "numpy", "scipy", "lightning", "timm", "kornia", "pycolmap", "faiss-cpu", "hydra-core", "nh3")
found = []
for name in packages:
    try:
        found.append(f"{name} {metadata.version(name)}")
    except metadata.PackageNotFoundError:
        found.append(f"{name} MISSING")
print(f"device: {device}; " + ", ".join(found))
PY
}

finish() {
    say "== steps (seconds used of the GPU budget)"
    for line in "${steps[@]}"; do say "$line"; done
    say "== total $((SECONDS - started_all)) s; budgets $budgets s$([ "$REHEARSE" = 1 ] && echo " (rehearsal)")"
    exit $status
}
