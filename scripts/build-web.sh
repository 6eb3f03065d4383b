#!/usr/bin/env bash
# Build the browser viewer bundle into viewer-wasm/dist/:
#
#   dist/index.html, viewer.css,       copied from viewer-wasm/web/ (the viewer page and the
#   upload.html, upload.js, upload.css upload/catalog page)
#   dist/pkg/                          wasm-bindgen --target web output (voxstream_viewer.js + _bg.wasm)
#
#   bash scripts/build-web.sh
#
# Picks the wasm toolchain that is present:
#   - rustup with the wasm32-unknown-unknown target installed: plain `cargo build --target ...`
#   - otherwise Debian's rustc-web/cargo-web (+ rust-web-src, lld) with -Zbuild-std
#     (scripts/setup.sh installs either route).
# Idempotent: cargo rebuilds only what changed, wasm-bindgen runs only when the wasm changed,
# and files are copied only when they differ, so an unchanged tree takes a couple of seconds.
#
# Environment:
#   VOXSTREAM_WASM_TARGET_DIR  cargo target dir for the wasm build (default: <target>/wasm, kept
#                              apart so rustup's and Debian's compilers never share artifacts)
#   VOXSTREAM_LOCKED=1         pass --locked to cargo (CI)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
CARGO_HOME="${CARGO_HOME:-$HOME/.cargo}"
export PATH="$PATH:$CARGO_HOME/bin"
WASM_BINDGEN_VERSION="0.2.130"
TARGET="wasm32-unknown-unknown"
TARGET_DIR="${VOXSTREAM_WASM_TARGET_DIR:-${CARGO_TARGET_DIR:-$ROOT/target}/wasm}"
DIST="$ROOT/viewer-wasm/dist"

log() { printf 'build-web: %s\n' "$*" >&2; }
die() {
  printf 'build-web: ERROR: %s\n' "$*" >&2
  exit 1
}

LOCKED=()
[ "${VOXSTREAM_LOCKED:-0}" = "1" ] && LOCKED=(--locked)

# --- 1. the wasm module ----------------------------------------------------------------------
if command -v rustup >/dev/null 2>&1 && rustup target list --installed 2>/dev/null | grep -qx "$TARGET"; then
  log "rustup toolchain with $TARGET"
  CARGO_TARGET_DIR="$TARGET_DIR" cargo build --release --target "$TARGET" -p voxstream-viewer "${LOCKED[@]}"
else
  [ -x /usr/bin/rustc ] && [ -x /usr/bin/cargo ] ||
    die "no $TARGET toolchain: run 'rustup target add $TARGET', or bash scripts/setup.sh (Debian rustc-web route)"
  WASM_LD="${VOXSTREAM_WASM_LD:-}"
  if [ -z "$WASM_LD" ]; then
    for candidate in /usr/lib/llvm-22/bin/wasm-ld /usr/lib/llvm-*/bin/wasm-ld "$(command -v wasm-ld || true)"; do
      if [ -n "$candidate" ] && [ -x "$candidate" ]; then
        WASM_LD="$candidate"
        break
      fi
    done
  fi
  [ -n "$WASM_LD" ] || die "wasm-ld not found (Debian: apt-get install lld-22), or set VOXSTREAM_WASM_LD"
  log "Debian toolchain ($(/usr/bin/rustc --version)), -Zbuild-std, linker $WASM_LD"
  RUSTC=/usr/bin/rustc RUSTC_BOOTSTRAP=1 CARGO_TARGET_DIR="$TARGET_DIR" \
    CARGO_TARGET_WASM32_UNKNOWN_UNKNOWN_LINKER="$WASM_LD" \
    /usr/bin/cargo build --release --target "$TARGET" -Zbuild-std=std,panic_abort -p voxstream-viewer "${LOCKED[@]}"
fi
WASM="$TARGET_DIR/$TARGET/release/voxstream_viewer.wasm"
[ -f "$WASM" ] || die "cargo did not produce $WASM"

# --- 2. JS bindings ------------------------------------------------------------------------------
command -v wasm-bindgen >/dev/null 2>&1 ||
  die "wasm-bindgen not found: cargo install wasm-bindgen-cli --version $WASM_BINDGEN_VERSION (or bash scripts/setup.sh)"
have="$(wasm-bindgen --version | awk '{print $2}')"
[ "$have" = "$WASM_BINDGEN_VERSION" ] ||
  die "wasm-bindgen CLI is $have, the crate is $WASM_BINDGEN_VERSION: cargo install wasm-bindgen-cli --version $WASM_BINDGEN_VERSION --force"
PKG="$DIST/pkg"
if [ ! -f "$PKG/voxstream_viewer_bg.wasm" ] || [ ! -f "$PKG/voxstream_viewer.js" ] || [ "$WASM" -nt "$PKG/voxstream_viewer_bg.wasm" ]; then
  log "wasm-bindgen → ${PKG#"$ROOT"/}"
  rm -rf "$PKG.tmp"
  wasm-bindgen --target web --no-typescript --out-dir "$PKG.tmp" "$WASM"
  rm -rf "$PKG"
  mv "$PKG.tmp" "$PKG"
else
  log "wasm-bindgen output is up to date"
fi

# --- 3. the page ---------------------------------------------------------------------------------
mkdir -p "$DIST"
for f in "$ROOT"/viewer-wasm/web/*; do
  dest="$DIST/$(basename "$f")"
  cmp -s "$f" "$dest" 2>/dev/null || cp "$f" "$dest"
done
log "bundle ready: ${DIST#"$ROOT"/} ($(du -sh "$PKG/voxstream_viewer_bg.wasm" | cut -f1) wasm)"
