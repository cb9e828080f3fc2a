#!/usr/bin/env bash
# The quality runs, before a release: full training schedules on the shared benchmark
# scenes, each scored by `nerf eval` and held to a floor a little below the figures in
# docs/benchmarks.md, and the test suite's long comparisons (`cargo test --release`
# keeps only short runs; the tests marked `#[ignore]` are the long ones). About 1.5 hours
# on 2 cores; much less on a GPU with DEVICE=wgpu.
#
#   scripts/quality.sh                  # every run
#   scripts/quality.sh lego fox         # some of them: tests, lego, barf, fox, beer, demo
#
# DATA (default ../shared/data) holds the scenes, OUT (default quality_runs) gets the runs.
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${DATA:-../shared/data}
OUT=${OUT:-quality_runs}
DEVICE=${DEVICE:-auto}
cargo build --release -q
NERF=$PWD/target/release/nerf
mkdir -p "$OUT"
failed=0

# The mean PSNR a `nerf eval` wrote into RUN/eval_test/metrics.json.
mean_psnr() {
  grep -o '"mean_psnr": *[0-9.]*' "$1/eval_test/metrics.json" | head -1 | grep -o '[0-9.]*$'
}

# train NAME FLOOR TRAIN_ARGS...: trains OUT/NAME (fresh), evaluates it, checks the floor.
run() {
  local name=$1 floor=$2
  shift 2
  if [ ! -d "$DATA" ]; then
    echo "no $DATA: the quality runs need the shared benchmark scenes"
    exit 1
  fi
  rm -rf "${OUT:?}/$name"
  echo "== $name: nerf train $*"
  "$NERF" train --device "$DEVICE" --val-every 0 --out "$OUT/$name" "$@"
  "$NERF" eval --device "$DEVICE" --run "$OUT/$name" --every 8
  local psnr
  psnr=$(mean_psnr "$OUT/$name")
  if awk -v p="$psnr" -v f="$floor" 'BEGIN { exit !(p >= f) }'; then
    echo "== $name: $psnr dB (floor $floor dB): ok"
  else
    echo "== $name: $psnr dB is below its floor of $floor dB"
    failed=1
  fi
}

wanted=${*:-tests lego barf fox beer demo}
for w in $wanted; do
  case $w in
    tests)
      echo "== tests: cargo test --release -- --ignored"
      cargo test --release -q -- --ignored || failed=1
      ;;
    lego) run lego 31.0 --data "$DATA/lego_400" ;;
    barf) run barf 29.5 --data "$DATA/lego_400" --perturb-poses 0.15 --refine-cameras ;;
    fox) run fox 26.5 --data "$DATA/ngp_fox" --downscale 4 ;;
    beer) run beer 24.0 --data "$DATA/llff_beer" --spherify --downscale 4 ;;
    demo)
      rm -rf "$OUT/demo"
      (mkdir -p "$OUT/demo" && cd "$OUT/demo" && "$NERF" demo --device "$DEVICE")
      ;;
    *) echo "unknown run $w (tests, lego, barf, fox, beer, demo)"; exit 2 ;;
  esac
done
exit $failed
