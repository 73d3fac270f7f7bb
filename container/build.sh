#!/usr/bin/env bash
# Build TrojAI's container for a fitted detector: container/build.sh DETECTOR_FOLDER [IMAGE.sif]
# DETECTOR_FOLDER is what `rlbackdoors detect fit` or `detect configure` wrote (detector.json,
# arrays.npz, metaparameters.json, metaparameters_schema.json). Needs apptainer (or singularity).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(dirname "$here")"
det="${1:?usage: container/build.sh DETECTOR_FOLDER [IMAGE.sif]}"
image="${2:-detector.sif}"
case "$image" in /*) ;; *) image="$PWD/$image" ;; esac
for f in detector.json metaparameters.json metaparameters_schema.json; do
  [ -f "$det/$f" ] || { echo "rlbackdoors: error: $det holds no $f (fit it with rlbackdoors detect fit)" >&2; exit 2; }
done
builder="$(command -v apptainer || command -v singularity || true)"
[ -n "$builder" ] || { echo "rlbackdoors: error: neither apptainer nor singularity is installed" >&2; exit 2; }
ctx="$(mktemp -d)"
trap 'rm -rf "$ctx"' EXIT
mkdir -p "$ctx/rlbackdoors" "$ctx/learned_parameters"
cp -r "$root/src" "$root/pyproject.toml" "$root/constraints.txt" "$root/README.md" "$ctx/rlbackdoors/"
cp "$det"/detector.json "$ctx/learned_parameters/"
[ -f "$det/arrays.npz" ] && cp "$det/arrays.npz" "$ctx/learned_parameters/"
cp "$det/metaparameters.json" "$det/metaparameters_schema.json" "$ctx/"
cp "$here/entrypoint.py" "$here/detector.def" "$ctx/"
(cd "$ctx" && "$builder" build "$image" detector.def)
echo "wrote $image"
