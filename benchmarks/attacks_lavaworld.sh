#!/usr/bin/env bash
# Issue 33's measurement: every attack on LavaWorld FC, seeds 0-9, the env-mix reference in the same
# session (CPU minutes per model are compared against it). Resumable: rerun it after a kill and every
# finished seed is read, every interrupted one resumes from its checkpoint. One run at a time, at nice.
#   bash benchmarks/attacks_lavaworld.sh [SEEDS]      -> benchmarks/results/recipes/attack-lavaworld-fc-*.json
set -euo pipefail
cd "$(dirname "$0")/.."
SEEDS=${1:-10}
PY=.venv/bin/python
for attack in envmix trojdrl sleepernets badrl action_target; do
  nice -n 10 "$PY" benchmarks/recipe_seeds.py "attack-lavaworld-fc-$attack" --seeds "$SEEDS" --workers 1 -- \
    --env lavaworld --arch fc --attack "$attack" --checkpoint-minutes 1 --quiet
done
