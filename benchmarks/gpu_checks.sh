#!/usr/bin/env bash
# The group trainer's checks and figures on a GPU machine, as one short script (a lent GPU is
# scarce: everything that needs it runs in one call, each part under its own time limit):
#   1. tests/test_group_cuda.py: the GPU path against the CPU group, reproducibility, kill/resume
#      (these tests skip on machines without CUDA, so CI never runs them);
#   2. models per hour, same run: a reference side (first --side) against groups on the GPU
#      (rlbackdoors bench zoo --side ...), each side saved as it finishes.
# Usage: bash benchmarks/gpu_checks.sh OUTDIR [FRAMES] [MODELS]
#   env: WORLDS   words "world[/arch][:models[:frames[:timeout_s]]]" (default "lavaworld"), each
#                 world's own architecture (default its first), size and time limit where a lease is short;
#        SIDES_<world, '-' as '_'>  that world's sides (default: SIDES, or SAFETY_SIDES for
#                 safety-car-goal); EVAL_EPISODES; TESTS_TIMEOUT; BENCH_TIMEOUT (default per world).
# Issue 55's judged work, with the engine group in all three grid worlds (2026-11-28; not yet run on
# a GPU), in about 8 minutes on a 16-core machine (each world under its own limit; the best CPU
# setting, groups of 8 on every core, against GPU groups at the issue's K):
#   WORLDS="lavaworld:256:50000:170 randomized-lavaworld/cnn:64:30000:110" EVAL_EPISODES=10 \
#   SIDES_lavaworld="8:cpu:16 256:cuda:1" SIDES_randomized_lavaworld="8:cpu:16 64:cuda:1" \
#   bash benchmarks/gpu_checks.sh OUT
set -uo pipefail
out=${1:?usage: gpu_checks.sh OUTDIR [FRAMES] [MODELS]}
frames=${2:-100000}
models=${3:-64}
cores=$(nproc)
sides=${SIDES:-"1:cpu:$cores 16:cuda:4 64:cuda:1 8:cpu:$cores"}
# Safety Car Goal (OPAC², single MuJoCo envs): GPU groups with each job's env copies in a pool of the other cores
safety_sides=${SAFETY_SIDES:-"1:cpu:$cores 16:cuda:1:$((cores - 1)) 64:cuda:1:$((cores - 1))"}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 || echo "no nvidia-smi"
    python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.is_available())"
    uptime
} | tee "$out/machine.txt"
timeout "${TESTS_TIMEOUT:-240}" python3 -m pytest -q -p no:cacheprovider --durations=0 tests/test_group_cuda.py 2>&1 | tee "$out/gpu_tests.log"
for entry in ${WORLDS:-lavaworld}; do  # e.g. WORLDS="lavaworld:64:100000:120 safety-car-goal:16:30000:150"
    IFS=: read -r world world_models world_frames world_timeout <<<"$entry"
    arch_args=()
    if [[ "$world" == */* ]]; then arch_args=(--arch "${world#*/}"); world=${world%%/*}; fi
    var="SIDES_${world//-/_}"
    if [ -n "${!var:-}" ]; then world_sides=${!var}; elif [ "$world" = safety-car-goal ]; then world_sides=$safety_sides; else world_sides=$sides; fi
    args=()
    for side in $world_sides; do args+=(--side "$side"); done
    timeout "${world_timeout:-${BENCH_TIMEOUT:-420}}" python3 -m rlbackdoors.cli bench zoo --env "$world" --models "${world_models:-$models}" \
        --frames "${world_frames:-$frames}" "${args[@]}" "${arch_args[@]}" ${EVAL_EPISODES:+--eval-episodes "$EVAL_EPISODES"} \
        --json "$out/bench_zoo_${world}${arch_args[1]:+_${arch_args[1]}}_gpu.json" 2>&1 | tee -a "$out/bench.log"
done
