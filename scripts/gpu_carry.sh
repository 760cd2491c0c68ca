#!/bin/bash
# Prepare, on this machine (with network), the folder a GPU machine without network needs for
# scripts/gpu_train.sh (README, "Training on a GPU"): wheels for CPython 3.12 (mujoco 4.0.0 is three wheels,
# plus glfw, pyopengl, webdataset, braceexpand), Debian's EGL loader packages for amd64, the compiled gravity
# plugin of this checkout, its commit (source_git), and the weights to start from with their leg.json.
#   scripts/gpu_carry.sh [--init WEIGHTS] [--target-init WEIGHTS] [--leg N] [--carry DIR]   (DIR: .gpu-carry)
# --init: weights to start the next leg from (e.g. the last leg's $OUT/detector.safetensors, its leg.json beside
# it is copied too); default: models/detector.safetensors at leg 0. --target-init: another target's keypoint
# weights for a TARGET leg (init/target.safetensors; none: that leg starts fresh). --leg N: the leg the init
# weights ended (init/leg.json {"leg": N}, over any leg.json beside them), so the next leg's data seeds move on:
# weights kept in models/ have no leg.json beside them. About 27 MB; name the folder in `carry`.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
CARRY=$ROOT/.gpu-carry
INIT=
TARGET_INIT=
LEG_N=
while [ $# -gt 0 ]; do
  case $1 in
    --init) INIT=$2; shift 2;;
    --target-init) TARGET_INIT=$2; shift 2;;
    --leg) LEG_N=$2; shift 2;;
    --carry) CARRY=$2; shift 2;;
    *) echo "gpu_carry: unknown argument $1" >&2; exit 2;;
  esac
done
if [ -n "$LEG_N" ] && ! [[ $LEG_N =~ ^[0-9]+$ ]]; then
  echo "gpu_carry: --leg $LEG_N: expected the leg number the init weights ended (0, 1, 2, ...)" >&2; exit 2
fi
if [ -n "$LEG_N" ] && [ -z "$INIT$TARGET_INIT" ]; then
  echo "gpu_carry: --leg $LEG_N without --init or --target-init: give the weights that leg ended with" >&2; exit 2
fi
PY=${PY:-$ROOT/.venv/bin/python}
mkdir -p "$CARRY/wheels" "$CARRY/debs" "$CARRY/plugin" "$CARRY/init"
WEBDATASET=$("$PY" -c "import webdataset; print(webdataset.__version__)")
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d "$CARRY/wheels" \
    mujoco==4.0.0 mujoco-core==4.0.0 mujoco-studio==4.0.0 glfw pyopengl "webdataset==$WEBDATASET" braceexpand
# EGL: the loader packages (the NVIDIA driver's EGL vendor library is on the GPU machine)
O="-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/gpu-carry-apt"
mkdir -p /tmp/gpu-carry-apt/partial
apt-get $O update -qq
(cd "$CARRY/debs" && apt-get $O download -qq libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
cp "$ROOT"/datagen/plugin/_relative_gravity*.so "$CARRY/plugin/"
# the commit the GPU machine's copy is (it has no .git): recorded by its runs as their git hash
GIT=$(git -C "$ROOT" rev-parse HEAD)
[ -n "$(git -C "$ROOT" status --porcelain --untracked-files=no)" ] && GIT="$GIT+dirty"
echo "$GIT" > "$CARRY/source_git"
rm -f "$CARRY/init/detector.safetensors" "$CARRY/init/target.safetensors" "$CARRY/init/leg.json"
for pair in "detector:$INIT" "target:$TARGET_INIT"; do
  W=${pair#*:}
  [ -z "$W" ] && continue
  cp "$W" "$CARRY/init/${pair%%:*}.safetensors"
  LEGF=$(dirname "$W")/leg.json
  [ -f "$LEGF" ] && cp "$LEGF" "$CARRY/init/leg.json"
done
[ -n "$LEG_N" ] && echo "{\"leg\": $LEG_N}" > "$CARRY/init/leg.json"
du -sh "$CARRY"; ls "$CARRY"/*
