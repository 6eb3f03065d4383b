#!/usr/bin/env bash
# Run every check voxstream has:
#
#   bash scripts/test.sh
#
#   1. scripts/setup.sh          installs what is missing (quick when all is there)
#   2. cargo fmt --check         formatting (rustfmt.toml at the root)
#   3. cargo clippy -D warnings  all targets of the workspace
#      cargo check fuzz/          the fuzz targets still compile (not run: scripts/fuzz.sh)
#   4. scripts/build-web.sh      wasm viewer bundle into viewer-wasm/dist (the browser test serves it)
#   5. scripts/cluster.sh tools  Garage (compiled once, cached outside the clone) and nginx-light
#      cargo test --workspace    unit, property, server integration, native render on lavapipe,
#                                browser end-to-end (headless Chromium, SwiftShader WebGPU)
#   6. scripts/schemathesis.sh   the HTTP API against its OpenAPI document: schemathesis' coverage,
#                                fuzzing and stateful phases on a fresh server, zero failures, plus a
#                                negative control (a wrong document must fail); about a minute
#
# Every step runs even when an earlier one failed (except setup), and the script exits non-zero
# if any failed, listing which. Extra arguments go to `cargo test` (e.g. `-- --nocapture`).
# Environment: VOXSTREAM_TEST_PROFILE=release runs the tests with --release (default: dev
# profile, which is optimised enough: opt-level 1, dependencies at 2).
set -uo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT" || exit 1
CARGO_HOME="${CARGO_HOME:-$HOME/.cargo}"
export PATH="$CARGO_HOME/bin:$PATH"

log() { printf '\n=== test: %s\n' "$*" >&2; }

bash scripts/setup.sh || {
  echo "test: ERROR: scripts/setup.sh failed; nothing was tested" >&2
  exit 1
}

# Headless machines often lack a session runtime dir; Vulkan/Wayland probing then prints
# "XDG_RUNTIME_DIR is invalid" errors into the log. Give the tests a private one.
if [ -z "${XDG_RUNTIME_DIR:-}" ] || [ ! -d "${XDG_RUNTIME_DIR}" ]; then
  XDG_RUNTIME_DIR="${CARGO_TARGET_DIR:-$ROOT/target}/xdg-runtime"
  mkdir -p "$XDG_RUNTIME_DIR" && chmod 700 "$XDG_RUNTIME_DIR"
  export XDG_RUNTIME_DIR
fi

PROFILE_ARGS=()
case "${VOXSTREAM_TEST_PROFILE:-dev}" in
  dev) ;;
  release) PROFILE_ARGS=(--release) ;;
  *)
    echo "test: ERROR: VOXSTREAM_TEST_PROFILE must be dev or release" >&2
    exit 1
    ;;
esac

FAILED=()
step() {
  # step NAME CMD... : runs CMD, records NAME as failed when it exits non-zero.
  local name="$1"
  shift
  log "$name: $*"
  local start=$SECONDS
  if "$@"; then
    echo "test: $name ok ($((SECONDS - start))s)" >&2
  else
    echo "test: $name FAILED ($((SECONDS - start))s)" >&2
    FAILED+=("$name")
  fi
}

build_web() {
  [ -f scripts/build-web.sh ] || {
    echo "test: scripts/build-web.sh is missing" >&2
    return 1
  }
  bash scripts/build-web.sh || return 1
  [ -f viewer-wasm/dist/index.html ] || {
    echo "test: scripts/build-web.sh did not produce viewer-wasm/dist/index.html" >&2
    return 1
  }
}

shell_syntax() {
  local f rc=0
  for f in scripts/*.sh .ci/run; do bash -n "$f" || rc=1; done
  return $rc
}

node_syntax() {
  local f rc=0
  for f in tests/browser/*.mjs; do node --check "$f" || rc=1; done
  return $rc
}

# In CI, Cargo.lock must already be complete (a dependency added without its lock entry fails).
LOCKED=()
if [ "${CI:-}" = "true" ]; then
  LOCKED=(--locked)
  export VOXSTREAM_LOCKED=1 # scripts/build-web.sh
fi

step "fmt" cargo fmt --all -- --check
step "shell syntax" shell_syntax
step "node syntax" node_syntax
# The viewer before anything compiles the server: the server embeds viewer-wasm/dist (server/build.rs).
step "build-web" build_web
step "clippy" cargo clippy --workspace --all-targets "${LOCKED[@]}" -- -D warnings
# The fuzz crate is outside the workspace; type-check its targets against the current APIs
# (stable rustc, no libFuzzer C++ build: see DEVELOPERS.md, "Fuzzing"). Running them is scripts/fuzz.sh.
# Not --locked: fuzz/Cargo.lock follows the server's dependencies, which change without it.
step "fuzz targets compile" cargo check --manifest-path fuzz/Cargo.toml --no-default-features --bins
# Garage (compiled once into ~/.cache/voxstream-tools: about 9 minutes cold on 2 cores, instant warm)
# and nginx-light, which the object-store and cluster tests start as real processes.
step "cluster tools (garage, nginx)" bash scripts/cluster.sh tools
# --no-fail-fast: one failing test binary must not hide the others' results.
step "cargo test" cargo test --workspace --no-fail-fast "${LOCKED[@]}" "${PROFILE_ARGS[@]}" "$@"
# After cargo test, on the voxstream binary it built: `cargo build` alone would compile it again
# (without the dev-dependencies' features, which cargo test unifies in). --no-run is a no-op here.
api_contract() {
  cargo test --workspace --no-run -q "${LOCKED[@]}" "${PROFILE_ARGS[@]}" >/dev/null 2>&1 || {
    echo "test: the workspace's tests do not build; no binary to check" >&2
    return 1
  }
  local dir=debug
  [ "${VOXSTREAM_TEST_PROFILE:-dev}" = release ] && dir=release
  VOXSTREAM_BIN="${CARGO_TARGET_DIR:-$ROOT/target}/$dir/voxstream" bash scripts/schemathesis.sh
}
step "api contract (schemathesis)" api_contract

echo >&2
if [ "${#FAILED[@]}" -gt 0 ]; then
  echo "test: FAILED steps: ${FAILED[*]}" >&2
  exit 1
fi
echo "test: all steps passed (${SECONDS}s)" >&2
