#!/usr/bin/env bash
# The GPU figures of docs/benchmarks.md in one run, for a machine with a GPU that is lent
# for minutes: pack a release binary and the scenes into a folder here, carry it there, run.
#
#   scripts/gpu_figures.sh pack DIR     # here: binary (stripped), lego_400's training views and
#                                       # every 8th test view, ngp_fox downscaled 4x (about 50 MB)
#   DIR/gpu_figures.sh run DIR          # there: about 4.5 minutes on an H200
#   FOX_CPU=1 DIR/gpu_figures.sh run DIR  # fox on the CPU engine too (+90 s on 16 cores)
#   SAMPLES=4096 STEPS=16 WARMUP=2 MINUTES=0.05 SIZE=64 FRAMES=2 FOX_STEPS=20 \
#     DEVICE=cpu DIR/gpu_figures.sh run DIR   # a smoke test of the script, on the CPU engine
#
# `run` prints, with the adapter's name: training samples/s at 65,536 and 262,144 samples
# and where a step's host time goes (NERF_GPU_TRACE), the same through the fused training
# kernels at 262,144, lego_400 in 60 s with the defaults
# (test PSNR on 25 views, the GPU's peak memory), 800x800 frames/s through the layers and
# through the fused field, the paper model's step,
# and ngp_fox's 2000 steps with the real-capture defaults (and the step trace's last
# report), then without camera refinement. DATA (default ../shared/data) holds the scenes
# when packing; ffmpeg and python3 are needed there. The GPU machine needs a Vulkan loader
# (libvulkan1) beside its driver.
set -euo pipefail

pack() {
  local dir
  dir=$(realpath -m "$1")
  cd "$(dirname "$0")/.."
  local data=${DATA:-../shared/data}
  cargo build --release -q -p nerf-cli
  mkdir -p "$dir"
  cp target/release/nerf "$dir/nerf"
  strip "$dir/nerf"
  cp scripts/gpu_figures.sh "$dir/"
  rm -rf "$dir/lego_400" "$dir/fox4"
  mkdir -p "$dir/lego_400/test" "$dir/fox4/images"
  cp -r "$data/lego_400/train" "$data/lego_400/transforms_train.json" "$dir/lego_400/"
  python3 - "$data/lego_400" "$dir/lego_400" <<'EOF'
import json, shutil, sys
src, dst = sys.argv[1:]
d = json.load(open(f"{src}/transforms_test.json"))
d["frames"] = d["frames"][::8]
for f in d["frames"]:
    shutil.copy(f"{src}/{f['file_path'].lstrip('./')}.png", f"{dst}/test/")
json.dump(d, open(f"{dst}/transforms_test.json", "w"))
EOF
  for f in "$data"/ngp_fox/images/*; do
    ffmpeg -loglevel error -y -i "$f" -vf scale=iw/4:ih/4:flags=area -q:v 2 "$dir/fox4/images/$(basename "$f")"
  done
  python3 - "$data/ngp_fox/transforms.json" "$dir/fox4/transforms.json" <<'EOF'
import json, sys
d = json.load(open(sys.argv[1]))
for k in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
    d[k] = d[k] / 4
json.dump(d, open(sys.argv[2], "w"), indent=1)
EOF
  du -sh "$dir"
}

run() {
  local dir=$1
  local nerf=$dir/nerf lego=$dir/lego_400 gpu=${DEVICE:-wgpu} runs
  runs=$(mktemp -d)
  command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
  for samples in ${SAMPLES:-65536 262144}; do
    echo "== training, $samples samples a step"
    NERF_GPU_TRACE=1 "$nerf" bench --device "$gpu" --data "$lego" --samples "$samples" \
      --steps "${STEPS:-100}" --warmup-steps "${WARMUP:-300}" 2>&1 | grep -E "engine:|samples/s|training step|gpu training|rror" | tail -5
  done
  echo "== training through the fused field (NERF_GPU_TRAIN=fused), 262,144 samples a step"
  NERF_GPU_TRAIN=fused NERF_GPU_TRACE=1 "$nerf" bench --device "$gpu" --data "$lego" --samples 262144 \
    --steps "${STEPS:-100}" --warmup-steps "${WARMUP:-300}" 2>&1 | grep -E "samples/s|training step|fit|rror" | tail -4
  echo "== lego_400, ${MINUTES:-1} min with the defaults, 262,144 samples a step"
  local watch=""
  if command -v nvidia-smi >/dev/null; then
    nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 250 > "$runs/memory" &
    watch=$!
  fi
  "$nerf" train --data "$lego" --device "$gpu" --minutes "${MINUTES:-1}" --samples 262144 --val-every 0 \
    --out "$runs/lego" 2>&1 | grep -E "stopped after|rror"
  if [ -n "$watch" ]; then
    kill "$watch"
    echo "peak GPU memory: $(sort -n "$runs/memory" | tail -1) MiB"
  fi
  "$nerf" eval --run "$runs/lego" --device "$gpu" 2>&1 | grep -E "mean PSNR|rror"
  echo "== rendering ${SIZE:-800} wide"
  "$nerf" render --run "$runs/lego" --device "$gpu" --size "${SIZE:-800}" --frames "${FRAMES:-40}" 2>&1 | grep -E "frames/s|rror"
  echo "== the same, the fused field (NERF_GPU_FIELD=fused)"
  NERF_GPU_FIELD=fused "$nerf" render --run "$runs/lego" --device "$gpu" --size "${SIZE:-800}" \
    --frames "${FRAMES:-40}" --out "$runs/fused_frames" 2>&1 | grep -E "frames/s|rror"
  echo "== the paper model's step"
  "$nerf" bench --model vanilla --device "$gpu" --steps 10 2>&1 | grep -E "median|rror" | tail -2
  local devices=$gpu
  [ -n "${FOX_CPU:-}" ] && devices="$gpu cpu"
  for device in $devices; do
    echo "== ngp_fox (downscaled 4x), ${FOX_STEPS:-2000} steps, the real-capture defaults, $device"
    NERF_GPU_TRACE=1 "$nerf" train --data "$dir/fox4" --steps "${FOX_STEPS:-2000}" --seed 0 \
      --device "$device" --val-every 0 --out "$runs/fox_$device" 2>&1 |
      grep -E "stopped after|gpu training|rror" | tail -2
  done
  "$nerf" eval --run "$runs/fox_$gpu" --device "$gpu" 2>&1 | grep -E "mean PSNR|rror"
  # What refinement still costs a GPU step: the same run with the cameras as given.
  echo "== ngp_fox as above, --no-refine-cameras, $gpu"
  NERF_GPU_TRACE=1 "$nerf" train --data "$dir/fox4" --steps "${FOX_STEPS:-2000}" --seed 0 \
    --device "$gpu" --no-refine-cameras --val-every 0 --out "$runs/fox_given" 2>&1 |
    grep -E "stopped after|gpu training|rror" | tail -2
  rm -rf "$runs"
}

case "${1:-}" in
  pack) pack "${2:?a folder to pack into}" ;;
  run) run "${2:?the packed folder}" ;;
  *) sed -n '2,20p' "$0"; exit 2 ;;
esac
