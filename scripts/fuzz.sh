#!/usr/bin/env bash
# Build and run every fuzz target in fuzz/, one after the other:
#
#   bash scripts/fuzz.sh [SECONDS] [TARGET...]
#
# SECONDS per target (default 180); TARGETs default to all (`cargo fuzz list`). Needs cargo-fuzz
# (`cargo install cargo-fuzz --locked`) and either a nightly toolchain or, as here, stable with
# RUSTC_BOOTSTRAP=1 for -Zsanitizer=address. Inputs that crash land in fuzz/artifacts/<target>/,
# the growing corpus in fuzz/corpus/<target>/ (neither is committed); the committed seeds are
# fuzz/seeds/<target>/. Prints executions, run time and crashes per target; exits non-zero when
# any target found something. libFuzzer stops at the first crash; FUZZ_KEEP_GOING=1 runs in fork
# mode instead (-fork=1 -ignore_crashes=1 ...), so one known crash does not end the run and every
# crashing input is written.
set -uo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT" || exit 1
CARGO_HOME="${CARGO_HOME:-$HOME/.cargo}"
export PATH="$CARGO_HOME/bin:$PATH"
export RUSTC_BOOTSTRAP=1
# The fuzz crate is outside the workspace; keep its sanitizer build apart from the normal one.
FUZZ_TARGET="${CARGO_TARGET_DIR:-$ROOT/target}/fuzz"

DURATION="${1:-180}"
shift || true
case "$DURATION" in '' | *[!0-9]*)
  echo "fuzz: SECONDS must be a whole number, not '$DURATION'" >&2
  exit 2
  ;;
esac

if ! cargo fuzz --version >/dev/null 2>&1; then
  echo "fuzz: cargo-fuzz is missing: cargo install cargo-fuzz --locked" >&2
  exit 1
fi

TARGETS=("$@")
if [ "${#TARGETS[@]}" -eq 0 ]; then
  mapfile -t TARGETS < <(cargo fuzz list --fuzz-dir fuzz)
fi

cargo fuzz build --fuzz-dir fuzz --target-dir "$FUZZ_TARGET" || exit 1

KEEP_GOING=()
if [ "${FUZZ_KEEP_GOING:-0}" = "1" ]; then
  KEEP_GOING=(-fork=1 -ignore_crashes=1 -ignore_timeouts=1 -ignore_ooms=1)
fi

LOGS="$FUZZ_TARGET/logs"
mkdir -p "$LOGS"
FOUND=()
SUMMARY=()
for t in "${TARGETS[@]}"; do
  mkdir -p "fuzz/corpus/$t" "fuzz/artifacts/$t"
  before=$(find "fuzz/artifacts/$t" -type f | wc -l)
  echo "fuzz: $t for ${DURATION}s" >&2
  # -timeout: an input that takes 10 s is a finding (quadratic parsing) on these small inputs.
  start=$SECONDS
  cargo fuzz run --fuzz-dir fuzz --target-dir "$FUZZ_TARGET" --jobs 1 "$t" "fuzz/corpus/$t" "fuzz/seeds/$t" -- \
    -max_total_time="$DURATION" -max_len=16384 -timeout=10 -print_final_stats=1 "${KEEP_GOING[@]}" \
    >"$LOGS/$t.log" 2>&1
  rc=$?
  after=$(find "fuzz/artifacts/$t" -type f | wc -l)
  # "#N" opens every libFuzzer status line, in plain and in fork mode: N = executions so far.
  runs=$(grep -oE '^#[0-9]+' "$LOGS/$t.log" | tail -1 | tr -d '#')
  crashes=$((after - before))
  SUMMARY+=("$t: ${runs:-?} executions in $((SECONDS - start)) s, exit $rc, new crash files: $crashes; log $LOGS/$t.log")
  if [ "$rc" -ne 0 ] || [ "$crashes" -gt 0 ]; then
    FOUND+=("$t")
    grep -E 'panicked|ERROR: |SUMMARY|Test unit written' "$LOGS/$t.log" | head -20 >&2
  fi
done

printf '%s\n' "${SUMMARY[@]}"
if [ "${#FOUND[@]}" -gt 0 ]; then
  echo "fuzz: findings in: ${FOUND[*]} (inputs under fuzz/artifacts/)" >&2
  exit 1
fi
