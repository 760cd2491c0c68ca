#!/bin/bash
# One leg of detector training on a borrowed GPU machine (issue 26; README, "Training on a GPU"). Run from the
# repository root there, with the folder scripts/gpu_carry.sh made here carried (default .gpu-carry):
#   scripts/gpu_train.sh                          # on the GPU machine: everything, about 9 minutes
#   OUT=/tmp/o TOTAL_S=300 GEN_S=60 RATE=1 VAL_IMAGES=3 VAL_S=60 BATCH=2 WORKERS=1 DEVICE=cpu \
#       MUJOCO_GL=osmesa NO_INSTALL=1 SCENARIOS="default slow-tumble" PY=$PWD/.venv/bin/python scripts/gpu_train.sh
#                                                 # a dry run on a CPU machine with the project's environment
# Steps: install the carried wheels (mujoco, glfw, pyopengl for cp312, webdataset, braceexpand) into a scratch
# folder; unpack the carried EGL loader packages and run ldconfig; lay the package out without a build
# (scripts/gpu_layout.py, the compiled gravity plugin from the carry); check torch, CUDA and EGL; then
# scripts/gpu_train.py: fresh data on every core for GEN_S seconds with seeds of leg N+1 (N from the carried
# init/leg.json), `envisat train --init ... --workers (cores-2) --bf16 --time-budget-s` for what is left of
# TOTAL_S, and detector.safetensors, leg.json, metrics.jsonl, config.json, generate.json, candidates.json (the
# leg's weights checked against its init on held-out views) and gpu_train.log written to $OUT. The next leg
# carries $OUT's detector.safetensors and leg.json as init/ (gpu_carry.sh --init) when they beat their init.
# env: CARRY, OUT, TOTAL_S (540), GEN_S (170), RATE (expected 1024-px images/s: 170), DEVICE (cuda),
#      WORKERS (cores-2), BATCH (64), VAL_IMAGES (60), VAL_S (50), SCENARIOS (all), INIT, PY (python3), NO_INSTALL,
#      MUJOCO_GL (egl), WORK (/tmp/gpu-leg), ONLINE (set: `envisat train --online --looks` from frames rendered
#      as it trains, no shards; the schedule constant then cooled down, pre_cooldown.safetensors and
#      ema.safetensors back), TARGET (a target file relative to the checkout, e.g. models/upper_stage.xml: its
#      keypoint detector, `envisat train --target`, online, from the carried init/target.safetensors or, with
#      none, fresh from BACKBONE's backbone ('shipped', ENVISAT's, by default; 'none': from scratch);
#      no held-out check, which is ENVISAT's: calibrate and evaluate --target here), SPEED_S (seconds of bench/train_speed.py's GPU rows first, inside TOTAL_S; its
#      train_speed.json written row by row, so a row cut at the limit loses only itself), PACK (set: every output
#      but gpu_train.log and train_speed.json in one leg.tar, since a borrowed machine returns at most 8 files)
# A lease (issue 38, item 5), from the last leg's pre-cooldown weights carried as init (scripts/gpu_carry.sh
# --init RUN/pre_cooldown.safetensors):  ONLINE=1 SPEED_S=90 PACK=1 TOTAL_S=530 OUT=$OUT scripts/gpu_train.sh
set -o pipefail
T0=$(date +%s)
ROOT=$(cd "$(dirname "$0")/.." && pwd)
CARRY=${CARRY:-$ROOT/.gpu-carry}
OUT=${OUT:-$ROOT/out/gpu-leg}
TOTAL_S=${TOTAL_S:-540}
WORK=${WORK:-/tmp/gpu-leg}
PY=${PY:-python3}
export MUJOCO_GL=${MUJOCO_GL:-egl}
mkdir -p "$OUT" "$WORK"
LOG="$OUT/gpu_train.log"
exec > >(tee "$LOG") 2>&1
echo "gpu_train: $(date -u +%FT%TZ), $(nproc) cores, MUJOCO_GL=$MUJOCO_GL, budget ${TOTAL_S} s"
if [ -z "$NO_INSTALL" ]; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$WORK/site" \
      "$CARRY"/wheels/*.whl || { echo "gpu_train: wheel install failed"; exit 3; }
  export PYTHONPATH="$WORK/site${PYTHONPATH:+:$PYTHONPATH}"
fi
if [ "$MUJOCO_GL" = egl ] && ls "$CARRY"/debs/*.deb >/dev/null 2>&1; then
  for f in "$CARRY"/debs/*.deb; do dpkg -x "$f" /; done
  ldconfig
fi
$PY "$ROOT/scripts/gpu_layout.py" "$WORK/pkg" --plugin-from "$CARRY/plugin" || exit 4
export PYTHONPATH="$WORK/pkg:$PYTHONPATH"
cd "$WORK" || exit 4  # not the checkout: the laid-out package is the one imported
$PY -c "import mujoco, torch, envisat_pose; print('mujoco', mujoco.__version__, 'torch', torch.__version__, 'cuda',
torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')" || exit 5
if [ "$MUJOCO_GL" = egl ]; then
  $PY -c "
from mujoco.egl import GLContext
c = GLContext(64, 64); c.make_current()
from OpenGL import GL; print('EGL:', GL.glGetString(GL.GL_RENDERER).decode())" || { echo "gpu_train: EGL failed"; exit 6; }
fi
# the laid-out copy has no .git: its runs record the commit gpu_carry.sh wrote
[ -f "$CARRY/source_git" ] && export ENVISAT_SOURCE_GIT=$(cat "$CARRY/source_git")
if [ -n "$TARGET" ]; then
  # another target's keypoint detector: from the carried init/target.safetensors when there is one, else fresh
  INIT=${INIT:-$CARRY/init/target.safetensors}
  LEG=$CARRY/init/leg.json
  if [ ! -f "$INIT" ]; then INIT=; LEG=; fi
  BACKBONE=${BACKBONE:-shipped}
  if [ -n "$INIT" ]; then BACKBONE=; fi  # 'none' passes on: envisat train's default for a fresh target is 'shipped'
else
  BACKBONE=
  INIT=${INIT:-$CARRY/init/detector.safetensors}
  LEG=$CARRY/init/leg.json
  if [ ! -f "$INIT" ]; then INIT=$ROOT/models/detector.safetensors; LEG=; fi
fi
echo "gpu_train: init ${INIT:+$(basename "$INIT") ($(sha256sum "$INIT" | cut -c1-12))}${INIT:-none (fresh${BACKBONE:+, backbone $BACKBONE})}${TARGET:+, target $TARGET}, setup took $(( $(date +%s) - T0 )) s"
if [ "${SPEED_S:-0}" -gt 0 ]; then
  echo "gpu_train: the speed benchmark's GPU rows for at most ${SPEED_S} s"
  timeout "$SPEED_S" $PY "$ROOT/bench/train_speed.py" --no-cpu --no-whole --gpu-batch-sizes 64 256 \
      --gpu-images 256 --gpu-shard-size 32 --gpu-step-steps 20 --out "$OUT/train_speed.json" \
      || echo "gpu_train: the speed benchmark ended with rc $? (its rows so far are in train_speed.json)"
fi
$PY "$ROOT/scripts/gpu_train.py" ${INIT:+--init "$INIT"} ${BACKBONE:+--backbone "$BACKBONE"} ${TARGET:+--target "$ROOT/$TARGET"} ${LEG:+--leg-file "$LEG"} --out "$OUT" --work "$WORK/leg" \
    --deadline-s $(( T0 + TOTAL_S )) --gen-s "${GEN_S:-170}" ${RATE:+--rate "$RATE"} --device "${DEVICE:-cuda}" \
    ${ONLINE:+--online} \
    ${VAL_IMAGES:+--validate-images "$VAL_IMAGES"} ${VAL_S:+--validate-s "$VAL_S"} \
    ${WORKERS:+--workers "$WORKERS"} ${BATCH:+--batch-size "$BATCH"} ${SCENARIOS:+--scenarios $SCENARIOS} || exit 7
if [ -n "$PACK" ]; then
  FILES=$(cd "$OUT" && ls | grep -v -x -e gpu_train.log -e train_speed.json -e leg.tar)
  (cd "$OUT" && tar -cf leg.tar $FILES && rm -f $FILES) || exit 8
  echo "gpu_train: packed into leg.tar: $(echo $FILES | tr '\n' ' ')"
fi
echo "gpu_train: done in $(( $(date +%s) - T0 )) s; in $OUT: $(ls "$OUT" | tr '\n' ' ')"
