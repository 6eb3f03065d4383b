#!/usr/bin/env bash
# GPU timing on a machine with a real Vulkan GPU and no Rust (DEVELOPERS.md, "Timing on a real GPU"):
#
#   bash scripts/gpu-timing.sh PAYLOAD.tar.xz OUT_DIR
#
# PAYLOAD holds bin/voxstream (release, stripped), optionally bin/voxstream-before (the build to
# compare with, timed in the same run), bin/viewer_bench, and scenes/ (an `ao-bench --scene-cache`
# directory with views at 256 and 1024). Each measurement is a step with its own timeout, skipped
# once DEADLINE seconds have passed; OUT_DIR/results.tgz is rewritten after every step, so a run cut
# short still returns what it measured. Environment: W, H (1920x1080), RUNS (20), DEADLINE (300),
# VK_DRIVER_FILES (found under /usr/local/nvidia or /usr/share if unset).
set -u
PAYLOAD=${1:?usage: gpu-timing.sh PAYLOAD.tar.xz OUT_DIR}
OUT=${2:?usage: gpu-timing.sh PAYLOAD.tar.xz OUT_DIR}
W=${W:-1920}
H=${H:-1080}
RUNS=${RUNS:-20}
DEADLINE=${DEADLINE:-300}
RES=$(mktemp -d)
WORK=$(mktemp -d)
mkdir -p "$OUT"
export XDG_RUNTIME_DIR="$WORK/xdg" WGPU_BACKEND=vulkan
mkdir -p "$XDG_RUNTIME_DIR" && chmod 700 "$XDG_RUNTIME_DIR"
if [ -z "${VK_DRIVER_FILES:-}" ]; then
  for j in /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json /usr/share/vulkan/icd.d/nvidia_icd.json /etc/vulkan/icd.d/nvidia_icd.json; do
    if [ -f "$j" ]; then
      export VK_DRIVER_FILES="$j"
      break
    fi
  done
fi
tar xJf "$PAYLOAD" -C "$WORK" || exit 1
cd "$WORK" || exit 1
{
  date -u
  nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.max.sm,memory.total --format=csv 2>&1
  echo "VK_DRIVER_FILES=${VK_DRIVER_FILES:-unset}"
} > "$RES/env.txt"
cat "$RES/env.txt"

save() { tar czf "$OUT/results.tgz" -C "$RES" .; }
step() {
  # step NAME TIMEOUT CMD... : stdout to NAME.out, stderr to NAME.log
  local name=$1 limit=$2
  shift 2
  local left=$((DEADLINE - SECONDS))
  if [ "$left" -lt 20 ]; then
    echo "SKIP $name (deadline)"
    return
  fi
  [ "$limit" -gt "$left" ] && limit=$left
  local t0=$SECONDS
  timeout "$limit" "$@" > "$RES/$name.out" 2> "$RES/$name.log"
  echo "== $name rc=$? $((SECONDS - t0))s"
  grep -E "^  |error" "$RES/$name.log" | cut -c1-150 | tail -12
  save
}
bench() {
  # bench NAME BINARY RESOLUTION SWEEP RUNS [ao-bench args...]
  local name=$1 bin=$2 res=$3 sweep=$4 runs=$5
  shift 5
  step "$name" 90 "$bin" ao-bench --time-only --scene-cache scenes --resolution "$res" --width "$W" --height "$H" \
    --sweep "$sweep" --timing-runs "$runs" --out-dir "$RES/$name" "$@"
}
bench default-256 ./bin/voxstream 256 default "$RUNS"
if [ -x ./bin/voxstream-before ]; then
  bench before-default-256 ./bin/voxstream-before 256 default "$RUNS"
fi
bench default-1024 ./bin/voxstream 1024 default "$RUNS"
if [ -x ./bin/viewer_bench ]; then
  step frames-dragon 30 ./bin/viewer_bench scenes/dragon-1024 close "${W}x${H}" --culled-only --no-budget-path --frame-times "$RUNS"
  step frames-conference 30 ./bin/viewer_bench scenes/conference-inside-1024 inside "${W}x${H}" --culled-only --no-budget-path --frame-times "$RUNS"
fi
V3=(--view cornell_box --view dragon --view conference_inside)
bench cones-256 ./bin/voxstream 256 cones 10 "${V3[@]}"
bench sparse-256 ./bin/voxstream 256 sparse-temporal 10 "${V3[@]}"
bench mode-256 ./bin/voxstream 256 mode 10 "${V3[@]}"
bench structure-256 ./bin/voxstream 256 structure 10 "${V3[@]}"
save
echo "done in ${SECONDS}s: $OUT/results.tgz"
