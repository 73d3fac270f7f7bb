#!/usr/bin/env bash
# Build TrojAI's container for a fitted detector:
#   container/build.sh DETECTOR_FOLDER [IMAGE.sif] [--plugin FILE]...
# DETECTOR_FOLDER is what `rlbackdoors detect fit` or `detect configure` wrote (detector.json,
# arrays.npz, metaparameters.json, metaparameters_schema.json). --plugin FILE: a Python file of
# one's own detectors (`detect ... --plugin FILE`), put in the image, where the entry point loads it
# before anything else (needed when the fitted detector is one of its own). Needs apptainer (or
# singularity). With RLBACKDOORS_STAGE=DIR it only writes the image's build context (what the image
# will hold: the package, the learned parameters, the plugins, entrypoint.py, detector.def) into DIR.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(dirname "$here")"
usage="usage: container/build.sh DETECTOR_FOLDER [IMAGE.sif] [--plugin FILE]..."
positional=()
plugins=()
while [ $# -gt 0 ]; do
  case "$1" in
    --plugin) [ $# -ge 2 ] || { echo "rlbackdoors: error: --plugin needs a file ($usage)" >&2; exit 2; }; plugins+=("$2"); shift 2 ;;
    --plugin=*) plugins+=("${1#--plugin=}"); shift ;;
    -*) echo "rlbackdoors: error: unknown option $1 ($usage)" >&2; exit 2 ;;
    *) positional+=("$1"); shift ;;
  esac
done
[ ${#positional[@]} -ge 1 ] && [ ${#positional[@]} -le 2 ] || { echo "rlbackdoors: error: $usage" >&2; exit 2; }
det="${positional[0]}"
image="${positional[1]:-detector.sif}"
case "$image" in /*) ;; *) image="$PWD/$image" ;; esac
for f in detector.json metaparameters.json metaparameters_schema.json; do
  [ -f "$det/$f" ] || { echo "rlbackdoors: error: $det holds no $f (fit it with rlbackdoors detect fit)" >&2; exit 2; }
done
for p in ${plugins[@]+"${plugins[@]}"}; do
  case "$p" in *.py) ;; *) echo "rlbackdoors: error: --plugin $p is not a Python file (.py)" >&2; exit 2 ;; esac
  [ -f "$p" ] || { echo "rlbackdoors: error: --plugin $p is not a file" >&2; exit 2; }
done

stage() {  # the build context in $1
  mkdir -p "$1/rlbackdoors" "$1/learned_parameters" "$1/plugins"
  cp -r "$root/src" "$root/pyproject.toml" "$root/constraints.txt" "$root/README.md" "$1/rlbackdoors/"
  cp "$det"/detector.json "$1/learned_parameters/"
  if [ -f "$det/arrays.npz" ]; then cp "$det/arrays.npz" "$1/learned_parameters/"; fi
  cp "$det/metaparameters.json" "$det/metaparameters_schema.json" "$1/"
  for p in ${plugins[@]+"${plugins[@]}"}; do cp "$p" "$1/plugins/"; done
  cp "$here/entrypoint.py" "$here/detector.def" "$1/"
}

if [ -n "${RLBACKDOORS_STAGE:-}" ]; then
  stage "$RLBACKDOORS_STAGE"
  echo "staged the build context in $RLBACKDOORS_STAGE"
  exit 0
fi
builder="$(command -v apptainer || command -v singularity || true)"
[ -n "$builder" ] || { echo "rlbackdoors: error: neither apptainer nor singularity is installed" >&2; exit 2; }
ctx="$(mktemp -d)"
trap 'rm -rf "$ctx"' EXIT
stage "$ctx"
(cd "$ctx" && "$builder" build "$image" detector.def)
echo "wrote $image"
