#!/usr/bin/env bash
# Block GET latency and throughput through one replica: a local store, Garage with the replica's
# cache off (--cache-size 1: no block fits, so nearly every GET is a ranged GET to Garage; the
# cold path), and Garage with a warm cache. Results: notes/BENCHMARKS.md, "Issue 12".
# Same scene (data/koala.obj at --resolution, default 512), loopback, the `loadtest` bench as the
# client. Prints one JSON object: {"local": {...}, "garage_cold": {...}, "garage_warm": {...}}.
#
#   bash scripts/bench-bucket.sh                       # release binaries (cargo build --release)
#   PROFILE=dev bash scripts/bench-bucket.sh            # the dev binaries already in target/debug
#   CLIENTS=50 SECONDS_PER_CASE=10 RESOLUTION=256 bash scripts/bench-bucket.sh
set -euo pipefail
cd "$(dirname "$0")/.."

PROFILE="${PROFILE:-release}"
CLIENTS="${CLIENTS:-64}"
SECONDS_PER_CASE="${SECONDS_PER_CASE:-15}"
RESOLUTION="${RESOLUTION:-512}"
TARGET="${CARGO_TARGET_DIR:-target}"
BIN_DIR="$TARGET/$([ "$PROFILE" = dev ] && echo debug || echo "$PROFILE")"

SCRIPT_NAME=bench-bucket
# shellcheck source=scripts/lib/preamble.sh
. scripts/lib/preamble.sh # the script has cd-ed to the repository root
GARAGE="$(bash scripts/garage.sh)"
cargo build --profile "$PROFILE" -p voxstream --bin voxstream >&2
cargo bench --profile "$PROFILE" -p voxstream --bench loadtest --no-run >&2
LOADTEST="$(ls -t "$BIN_DIR"/deps/loadtest-* | grep -v '\.d$' | head -1)"
VOX="$BIN_DIR/voxstream"

WORK="$(mktemp -d)"
PIDS=()
cleanup() {
  for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done
  rm -rf "$WORK"
}
trap cleanup EXIT

RPC=$(free_port) S3=$(free_port) ADMIN=$(free_port)
cat >"$WORK/garage.toml" <<EOF
metadata_dir = "$WORK/meta"
data_dir = "$WORK/data"
db_engine = "sqlite"
replication_factor = 1
rpc_bind_addr = "127.0.0.1:$RPC"
rpc_public_addr = "127.0.0.1:$RPC"
rpc_secret = "$(head -c 32 /dev/urandom | od -An -tx1 | tr -d ' \n')"
[s3_api]
s3_region = "garage"
api_bind_addr = "127.0.0.1:$S3"
root_domain = ".s3.garage.localhost"
[admin]
api_bind_addr = "127.0.0.1:$ADMIN"
EOF
RUST_LOG=warn "$GARAGE" -c "$WORK/garage.toml" server >"$WORK/garage.log" 2>&1 &
PIDS+=($!)
g() { "$GARAGE" -c "$WORK/garage.toml" "$@"; }
for _ in $(seq 100); do g node id -q >/dev/null 2>&1 && break; sleep 0.1; done
NODE="$(g node id -q | cut -d@ -f1)"
g layout assign -z dc1 -c 1G "$NODE" >/dev/null
g layout apply --version 1 >/dev/null
g bucket create scans >/dev/null
KEY="$(g key create bench)"
g bucket allow --read --write --owner scans --key bench >/dev/null
# Credentials in a file the processes read, never on a command line.
cat >"$WORK/s3.env" <<EOF
AWS_ENDPOINT_URL=http://127.0.0.1:$S3
AWS_ALLOW_HTTP=true
AWS_REGION=garage
AWS_ACCESS_KEY_ID=$(printf '%s\n' "$KEY" | sed -n 's/^Key ID: *//p')
AWS_SECRET_ACCESS_KEY=$(printf '%s\n' "$KEY" | sed -n 's/^Secret key: *//p')
EOF
export VOXSTREAM_S3_ENV_FILE="$WORK/s3.env"

log "building koala at $RESOLUTION into a local store and into Garage"
"$VOX" build data/koala.obj --resolution "$RESOLUTION" --name koala --out "$WORK/store" >&2
"$VOX" build data/koala.obj --resolution "$RESOLUTION" --name koala --out s3://scans/site >&2

# serve <store> [flags…]: starts a replica, sets BASE and PID.
serve() {
  local store="$1"
  shift
  RUST_LOG=warn "$VOX" serve --addr 127.0.0.1:0 --store "$store" "$@" >"$WORK/serve.out" 2>>"$WORK/serve.log" &
  PID=$!
  PIDS+=("$PID")
  for _ in $(seq 200); do grep -q listening "$WORK/serve.out" 2>/dev/null && break; sleep 0.05; done
  BASE="$(sed -n 's/^listening on //p' "$WORK/serve.out" | head -1)"
  [ -n "$BASE" ] || { cat "$WORK/serve.log" >&2; exit 1; }
}
load() { "$LOADTEST" --url "$BASE" --scene koala --pid "$PID" --clients "$CLIENTS" --seconds "$SECONDS_PER_CASE"; }
cache_line() { curl -sf "$BASE/metrics" | grep -E '^voxstream_store_cache_(hits|misses)_total\{kind="block"\}' | tr '\n' ' '; }

log "local store"
serve "$WORK/store" --read-only
LOCAL="$(load)"
kill "$PID"

log "Garage, cache off (every block is a ranged GET)"
serve s3://scans/site --cache-size 1
COLD="$(load)"
log "cold cache counters: $(cache_line)"
kill "$PID"

log "Garage, warm cache (one pass first, then measured)"
serve s3://scans/site --cache-size 1GiB
SECONDS_PER_CASE=3 load >/dev/null
WARM="$(load)"
log "warm cache counters: $(cache_line)"
kill "$PID"

printf '{"profile": "%s", "resolution": %s, "local": %s, "garage_cold": %s, "garage_warm": %s}\n' \
  "$PROFILE" "$RESOLUTION" "$LOCAL" "$COLD" "$WARM"
