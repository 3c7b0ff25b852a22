#!/usr/bin/env bash
# Train VIB variants of the arm preset side by side on a lent GPU machine, and bring back what acting needs.
#
#   benchmarks/gpu_train.sh NAME[:EXTRA_FLAGS] ...      (flags separated by commas)
#
# Expects, relative to the project root: wheels/*.whl (lerobot and the packages the machine lacks, plus this
# project's wheel) unless NO_INSTALL=1, the recording in data/arm_near, and $OUT for the results. Each
# variant trains `configs/policy/vib_arm_sim.json` with `lerobot-train` for STEPS steps (at most LIMIT
# seconds; the last saved checkpoint is kept either way). Per variant, $OUT gets the checkpoint without its
# weights (<name>_ckpt.tar.gz: configs, processors, training log) and the weights split in two files under
# 16 MiB (<name>_model.safetensors: `model.*`, <name>_ema.safetensors: the rest); `benchmarks/gpu_unpack.py`
# joins them back into a checkpoint.
set -uo pipefail
STEPS=${STEPS:-7000}
LIMIT=${LIMIT:-480}
WORKERS=${WORKERS:-7}
DEVICE=${DEVICE:-cuda}
SEED=${SEED:-1000}
OUT=${OUT:?set OUT}
if [ "${NO_INSTALL:-0}" != 1 ]; then
  PKG=/tmp/vib_pkgs
  pip install --quiet --no-index --no-deps --target "$PKG" wheels/*.whl || exit 1
  export PYTHONPATH="$PKG${PYTHONPATH:+:$PYTHONPATH}"
fi
export MUJOCO_GL=${MUJOCO_GL:-disable}
PY=${PY:-python}
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
nproc
date -u +%FT%TZ

mkdir -p outputs && rm -f outputs/gpu_times.txt
pids=()
for spec in "$@"; do
  name=${spec%%:*}
  extra=()
  [ "$spec" != "$name" ] && IFS=',' read -r -a extra <<< "${spec#*:}"
  rm -rf "outputs/gpu/$name"
  (
    start=$(date +%s)
    timeout "$LIMIT" "$PY" -m lerobot.scripts.lerobot_train --config_path=configs/policy/vib_arm_sim.json \
      --dataset.repo_id=local/vib_arm_grasp_block_scripted --dataset.root=data/arm_near \
      --output_dir="outputs/gpu/$name" --policy.device="$DEVICE" --num_workers="$WORKERS" --steps="$STEPS" \
      --seed="$SEED" "${extra[@]}" > "outputs/gpu_$name.log" 2>&1
    echo "$name rc=$? wall_s=$(( $(date +%s) - start ))" >> outputs/gpu_times.txt
  ) &
  pids+=($!)
done
wait "${pids[@]}"
cat outputs/gpu_times.txt
for spec in "$@"; do
  name=${spec%%:*}
  last=$(ls -d "outputs/gpu/$name"/checkpoints/[0-9]* 2>/dev/null | sort | tail -1)
  [ -z "$last" ] && { echo "$name: no checkpoint"; tail -20 "outputs/gpu_$name.log"; continue; }
  echo "$name: $last"
  "$PY" - "$last/pretrained_model/model.safetensors" "$OUT/${name}_model.safetensors" "$OUT/${name}_ema.safetensors" <<'PYEOF'
import sys
from safetensors.torch import load_file, save_file
state = load_file(sys.argv[1])
save_file({k: v for k, v in state.items() if k.startswith("model.")}, sys.argv[2])
save_file({k: v for k, v in state.items() if not k.startswith("model.")}, sys.argv[3])
PYEOF
  cp "outputs/gpu_$name.log" "$last/train.log"
  tar czf "$OUT/${name}_ckpt.tar.gz" --exclude=model.safetensors --exclude=optimizer_state.safetensors -C "$last" .
done
cp outputs/gpu_times.txt "$OUT/" 2>/dev/null
ls -la "$OUT"
