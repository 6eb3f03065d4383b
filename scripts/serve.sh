#!/usr/bin/env bash
# Build everything and serve the default scan:
#
#   bash scripts/serve.sh            then open http://127.0.0.1:8080/
#
# Steps: scripts/setup.sh (installs what is missing), scripts/build-web.sh (wasm viewer into
# viewer-wasm/dist), release build of the server (which embeds that viewer), `voxstream build data/koala.obj`
# into ./store when store/koala/manifest.json is missing or older than the mesh (or the server
# binary), then exec `voxstream serve`.
#
# Environment:
#   VOXSTREAM_ADDR   listen address (default 127.0.0.1:8080)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
CARGO_HOME="${CARGO_HOME:-$HOME/.cargo}"
export PATH="$CARGO_HOME/bin:$PATH"

SCRIPT_NAME=serve
# shellcheck source=scripts/lib/preamble.sh
. "$(dirname "${BASH_SOURCE[0]}")/lib/preamble.sh"

ADDR="${VOXSTREAM_ADDR:-127.0.0.1:8080}"
STORE="store"
MESH="data/koala.obj"
SCENE="koala"
WEB="viewer-wasm/dist"
TARGET_DIR="${CARGO_TARGET_DIR:-$ROOT/target}"
BIN="$TARGET_DIR/release/voxstream"

bash scripts/setup.sh || die "scripts/setup.sh failed (see above)"

# The viewer first: the server binary embeds viewer-wasm/dist (server/build.rs).
[ -f scripts/build-web.sh ] || die "scripts/build-web.sh is missing (the viewer build script)"
log "scripts/build-web.sh"
bash scripts/build-web.sh || die "scripts/build-web.sh failed (see above)"
[ -f "$WEB/index.html" ] || die "scripts/build-web.sh did not produce $WEB/index.html"

log "cargo build --release -p voxstream"
cargo build --release -p voxstream --bin voxstream || die "building the server failed"
[ -x "$BIN" ] || die "$BIN was not produced by the build"

[ -f "$MESH" ] || die "$MESH is missing"
MANIFEST="$STORE/$SCENE/manifest.json"
# Also rebuilt when the server binary is newer: a build takes about a second, and a scene written
# by an older build may not match the current format.
if [ ! -f "$MANIFEST" ] || [ "$MANIFEST" -ot "$MESH" ] || [ "$MANIFEST" -ot "$BIN" ]; then
  if [ -e "$STORE/$SCENE" ]; then
    log "$MANIFEST is older than $MESH or $BIN: rebuilding the scene"
    rm -rf -- "${STORE:?}/${SCENE:?}"
  fi
  mkdir -p "$STORE"
  log "voxstream build $MESH --out $STORE"
  "$BIN" build "$MESH" --out "$STORE" || die "voxstream build $MESH failed"
  [ -f "$MANIFEST" ] || die "voxstream build finished but $MANIFEST does not exist"
else
  log "$MANIFEST is up to date"
fi

log "serving $STORE on http://$ADDR/ (Ctrl-C to stop)"
exec "$BIN" serve --store "$STORE" --addr "$ADDR" # the viewer embedded in the binary
