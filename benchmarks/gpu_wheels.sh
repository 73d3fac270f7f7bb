#!/usr/bin/env bash
# The wheels a lent GPU machine lacks, fetched here (where pip reaches an index) into .whl/ at the
# repo root, so that `run` can carry them ("carry": [".whl"]) and gpu_checks.sh installs them there.
# Why: that machine is bare and offline. Its image already holds torch (CUDA), JAX, numba, numpy,
# scipy, scikit-learn, matplotlib, tqdm and pytest (/work/.library/device/KINDS.md), so only
# the worlds' engines and the schema checker travel, at the versions constraints.txt pins, for
# its CPython 3.12 on x86-64. mujoco-studio (the viewer, 13 MB) and pygame's extras stay behind:
# nothing here imports them; pygame-ce is needed (minigrid imports it). About 26 MB.
# Usage: bash benchmarks/gpu_wheels.sh   (then, in the run's command: bash benchmarks/gpu_checks.sh OUT)
set -euo pipefail
cd "$(dirname "$0")/.."
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >>.git/info/exclude
pin() { grep -i "^$1==" constraints.txt || { echo "gpu_wheels: $1 is not pinned in constraints.txt" >&2; exit 1; }; }
wanted=(gymnasium farama-notifications minigrid pygame-ce mujoco mujoco-core glfw pyopengl jsonschema jsonschema-specifications referencing rpds-py)
specs=()
for name in "${wanted[@]}"; do
    if grep -qi "^$name==" constraints.txt; then specs+=("$(pin "$name")"); else specs+=("$name"); fi
done
rm -rf .whl && mkdir -p .whl
platforms=()
for p in manylinux_2_35_x86_64 manylinux_2_34_x86_64 manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux1_x86_64; do
    platforms+=(--platform "$p")
done
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${platforms[@]}" -d .whl "${specs[@]}"
ls .whl
du -sh .whl
