#!/usr/bin/env bash
# Check the HTTP API against its own OpenAPI document (/api/openapi.json) with schemathesis (PyPI),
# a tool nobody here wrote:
#
#   bash scripts/schemathesis.sh              install if needed, build, run every phase (about a minute)
#   bash scripts/schemathesis.sh --install    only make sure the tools venv exists (scripts/setup.sh)
#   bash scripts/schemathesis.sh --venv       print the venv's path (installing it if needed)
#   bash scripts/schemathesis.sh --check      print the venv's path if it is complete, else exit 1
#
# What it does:
#   1. a Python virtualenv with the pinned tools of scripts/schemathesis/requirements.txt (schemathesis,
#      and tuspy for the tus client test) in a tools folder outside the clone, named after the
#      requirements' hash, so a warm machine skips the install (well under a second) and a changed pin
#      gets a fresh venv. Made in place and marked complete only when pip succeeded.
#   2. `voxstream` (the profile of VOXSTREAM_TEST_PROFILE, CARGO_TARGET_DIR honoured; VOXSTREAM_BIN=<path> uses a given binary),
#      and the default scan (data/koala.obj) built once into a temp dir.
#   3. negative control: schemathesis must FAIL against a deliberately wrong copy of the document (the
#      scene id pattern of GET /api/scenes/{id} removed, so ids the server rejects look valid). If it
#      passes, the harness cannot see contract failures and the step fails.
#   4. `voxstream serve --token ... --uploads-per-minute 0` on a fresh copy of the store, then
#      `st run --phases coverage,fuzzing`; a fresh store and server again for `--phases stateful` (the
#      first run deletes and renames scenes, and the stateful walk starts from the catalog); and the
#      coverage phase on a `--protect-read` server (its document requires the token for reading) and
#      on a `--read-only` one (its write routes answer 403 only).
#      Every check schemathesis has runs (`--checks` left at its default: all), zero failures required.
#
# Configuration and the stated exclusions are in scripts/schemathesis/schemathesis.toml (why each one);
# scripts/schemathesis/hooks.py adds the serializer for tus PATCH bodies (application/offset+octet-stream)
# and works around a CPython 3.11 parser bug that Hypothesis trips over. See DEVELOPERS.md, "API contract".
#
# Environment:
#   VOXSTREAM_TOOLS_DIR     where tools are kept (default ${XDG_CACHE_HOME:-$HOME/.cache}/voxstream-tools)
#   SCHEMATHESIS_EXAMPLES   examples per operation in the fuzzing phase (default 100)
#   SCHEMATHESIS_SEED       the seed (default 1, so CI is reproducible; `random` for a new one each run)
#   SCHEMATHESIS_KEEP=1     keep the work dir (store, server logs, reports) even when everything passed
#   VOXSTREAM_BIN           a voxstream binary to test instead of building one
#   VOXSTREAM_TEST_PROFILE  dev (default) or release: which profile's binary is built and tested
#   PYTHON                  the interpreter for the venv (default python3; 3.10 or newer)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
CARGO_HOME="${CARGO_HOME:-$HOME/.cargo}"
export PATH="$CARGO_HOME/bin:$PATH"

SCRIPT_NAME=schemathesis.sh
# shellcheck source=scripts/lib/preamble.sh
. "$(dirname "${BASH_SOURCE[0]}")/lib/preamble.sh"

HERE="$ROOT/scripts/schemathesis"
REQS="$HERE/requirements.txt"
TOOLS="${VOXSTREAM_TOOLS_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/voxstream-tools}"
PYTHON="${PYTHON:-python3}"
[ -f "$REQS" ] || die "$REQS is missing"
REQ_HASH="$(sha256sum "$REQS" | cut -c1-12)"
VENV="$TOOLS/pytools-$REQ_HASH"
STAMP="$VENV/.voxstream-complete"

# Complete (the stamp is written after pip succeeded) and its interpreter still runs. Cheap: importing
# schemathesis to ask `st --version` takes seconds on a busy machine.
venv_ok() { [ -f "$STAMP" ] && [ -x "$VENV/bin/st" ] && "$VENV/bin/python" -c '' >/dev/null 2>&1; }

ensure_venv() {
  venv_ok && return 0
  command -v "$PYTHON" >/dev/null 2>&1 || die "$PYTHON is missing (Debian: apt-get install python3 python3-venv)"
  mkdir -p "$TOOLS"
  # A venv records its own absolute path, so it is made where it stays; the stamp, written last, says
  # that pip finished. A half-made one (killed install) is removed and made again.
  rm -rf "$VENV"
  log "making $VENV: $(grep -v '^#' "$REQS" | head -2 | xargs) and their pinned dependencies (pip, about a minute)"
  "$PYTHON" -m venv "$VENV" >&2 ||
    die "$PYTHON -m venv failed (Debian: apt-get install python3-venv; scripts/setup.sh does)"
  "$VENV/bin/pip" install --quiet --disable-pip-version-check --no-input -r "$REQS" >&2 ||
    die "pip install -r $REQS failed (no network to PyPI?)"
  "$VENV/bin/st" --version >/dev/null || die "st is not runnable in $VENV"
  printf '%s\n' "$REQ_HASH" >"$STAMP"
  log "installed $("$VENV/bin/st" --version 2>&1)"
}

case "${1:-}" in
  --install)
    ensure_venv
    exit 0
    ;;
  --check)
    venv_ok || exit 1
    printf '%s\n' "$VENV"
    exit 0
    ;;
  --venv)
    ensure_venv
    printf '%s\n' "$VENV"
    exit 0
    ;;
  "") ;;
  *) die "unknown argument $1 (see the top of $0)" ;;
esac

ensure_venv
ST="$VENV/bin/st"

# --- the server binary and the default scan ---------------------------------------------------
if [ -n "${VOXSTREAM_BIN:-}" ]; then
  BIN="$VOXSTREAM_BIN"
else
  TARGET_DIR="${CARGO_TARGET_DIR:-$ROOT/target}"
  BUILD_ARGS=()
  [ "${CI:-}" = "true" ] && BUILD_ARGS+=(--locked)
  case "${VOXSTREAM_TEST_PROFILE:-dev}" in
    dev) BIN="$TARGET_DIR/debug/voxstream" ;;
    release)
      BIN="$TARGET_DIR/release/voxstream"
      BUILD_ARGS+=(--release)
      ;;
    *) die "VOXSTREAM_TEST_PROFILE must be dev or release" ;;
  esac
  log "cargo build -p voxstream --bin voxstream ${BUILD_ARGS[*]}"
  cargo build -q -p voxstream --bin voxstream "${BUILD_ARGS[@]}" >&2 || die "building voxstream failed"
fi
[ -x "$BIN" ] || die "$BIN is not an executable"

WORK="$(mktemp -d "${TMPDIR:-/tmp}/voxstream-schemathesis.XXXXXX")"
SERVER_PID=""
stop_server() {
  if [ -n "$SERVER_PID" ]; then
    kill "$SERVER_PID" 2>/dev/null || true
    wait "$SERVER_PID" 2>/dev/null || true
    SERVER_PID=""
  fi
}
OK=0
cleanup() {
  stop_server
  if [ "$OK" = 1 ] && [ "${SCHEMATHESIS_KEEP:-0}" != 1 ]; then
    rm -rf "$WORK"
  else
    log "logs, reports and stores kept in $WORK"
  fi
}
trap cleanup EXIT

"$BIN" build data/koala.obj --out "$WORK/pristine" >"$WORK/build.log" 2>&1 ||
  die "voxstream build data/koala.obj failed: $(tail -5 "$WORK/build.log")"

TOKEN="schemathesis-$$-$RANDOM"
BASE=""
# start_server NAME EXTRA_ARGS... : a server on a fresh copy of the pristine store; sets BASE.
start_server() {
  local name="$1"
  shift
  rm -rf "$WORK/store-$name"
  cp -a "$WORK/pristine" "$WORK/store-$name"
  "$BIN" serve --store "$WORK/store-$name" --addr 127.0.0.1:0 --token "$TOKEN" --uploads-per-minute 0 \
    --upload-idle-secs 5 --shutdown-secs 2 "$@" >"$WORK/serve-$name.out" 2>"$WORK/serve-$name.log" &
  SERVER_PID=$!
  local line
  for _ in $(seq 1 100); do
    line="$(head -1 "$WORK/serve-$name.out" 2>/dev/null || true)"
    if [ -n "$line" ]; then
      BASE="${line#listening on }"
      return 0
    fi
    kill -0 "$SERVER_PID" 2>/dev/null || die "voxstream serve exited: $(tail -5 "$WORK/serve-$name.log")"
    sleep 0.1
  done
  die "voxstream serve did not say where it listens within 10 s"
}

SEED_ARGS=(--seed "${SCHEMATHESIS_SEED:-1}")
[ "${SCHEMATHESIS_SEED:-1}" = random ] && SEED_ARGS=()
# run_st NAME SCHEMA ST_ARGS... : one schemathesis run with the project's config and hooks.
run_st() {
  local name="$1" schema="$2"
  shift 2
  local rc=0
  # From the work dir: schemathesis keeps a .schemathesis/ cache in its working directory.
  (cd "$WORK" && PYTHONPATH="$HERE${PYTHONPATH:+:$PYTHONPATH}" SCHEMATHESIS_HOOKS=hooks \
    "$ST" --config-file "$HERE/schemathesis.toml" run "$schema" \
    -H "Authorization: Bearer $TOKEN" --workers 2 --request-timeout 10 --no-color \
    --max-examples "${SCHEMATHESIS_EXAMPLES:-100}" "${SEED_ARGS[@]}" \
    --report junit --report-dir "$WORK/report-$name" "$@") >"$WORK/st-$name.log" 2>&1 || rc=$?
  return $rc
}

start=$SECONDS
FAILED=()

# --- negative control: a wrong document must fail ----------------------------------------------
start_server control
"$VENV/bin/python" - "$BASE/api/openapi.json" "$WORK/wrong.json" <<'EOF'
import json, sys, urllib.request
doc = json.load(urllib.request.urlopen(sys.argv[1]))
for p in doc["paths"]["/api/scenes/{id}"]["get"]["parameters"]:
    if p["name"] == "id":
        del p["schema"]["pattern"]  # now "A", "" or "../x" look valid, and the server (rightly) says 400
json.dump(doc, open(sys.argv[2], "w"))
EOF
if run_st control "$WORK/wrong.json" --url "$BASE" --phases coverage,fuzzing --include-operation-id get_scene; then
  log "FAILED: the negative control passed: schemathesis did not notice a wrong scene id pattern"
  FAILED+=("negative control")
elif ! grep -q "Schema-valid request rejected" "$WORK/st-control.log"; then
  log "FAILED: the negative control failed for another reason than the wrong pattern:"
  tail -30 "$WORK/st-control.log" >&2
  FAILED+=("negative control")
else
  log "negative control ok: a document without the scene id pattern fails (Schema-valid request rejected)"
fi
stop_server

# --- the real runs --------------------------------------------------------------------------------
# run_phase NAME PHASES SERVER_ARGS... : fresh store and server, then st on the served document.
run_phase() {
  local name="$1" phases="$2"
  shift 2
  start_server "$name" "$@"
  local t=$SECONDS
  if run_st "$name" "$BASE/api/openapi.json" --phases "$phases"; then
    log "$name ($phases) ok in $((SECONDS - t)) s: $(grep -E '^Test cases:' -A1 "$WORK/st-$name.log" | tail -1 | xargs)"
  else
    log "$name ($phases) FAILED; its report:"
    sed -n '/FAILURES\|ERRORS/,$p' "$WORK/st-$name.log" >&2
    FAILED+=("$name")
  fi
  if grep -q "panicked" "$WORK/serve-$name.log"; then
    log "$name: the server panicked:"
    grep -A5 "panicked" "$WORK/serve-$name.log" >&2
    FAILED+=("$name (server panic)")
  fi
  stop_server
}

run_phase fuzz coverage,fuzzing
run_phase stateful stateful
run_phase protect-read coverage --protect-read
run_phase read-only coverage --read-only

if [ "${#FAILED[@]}" -gt 0 ]; then
  log "FAILED: ${FAILED[*]} ($((SECONDS - start)) s)"
  exit 1
fi
OK=1
log "all passed in $((SECONDS - start)) s ($("$ST" --version 2>&1))"
