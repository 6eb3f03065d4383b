#!/usr/bin/env bash
# Build the browser viewer bundle into viewer-wasm/dist/:
#
#   dist/index.html, viewer.css,       copied from viewer-wasm/web/ (the viewer page and the
#   upload.html, upload.js, upload.css upload/catalog page)
#   dist/pkg/                          wasm-bindgen --target web output (voxstream_viewer.js + _bg.wasm)
#   dist/vendor/tus.min.js             tus-js-client's browser bundle (and its LICENSE), from the npm
#                                      package scripts/setup.sh installs in tests/browser
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

SCRIPT_NAME=build-web
# shellcheck source=scripts/lib/preamble.sh
. "$(dirname "${BASH_SOURCE[0]}")/lib/preamble.sh"

LOCKED=()
[ "${VOXSTREAM_LOCKED:-0}" = "1" ] && LOCKED=(--locked)

# --- 1. the wasm module ----------------------------------------------------------------------
if command -v rustup >/dev/null 2>&1 && rustup target list --installed 2>/dev/null | grep -qx "$TARGET"; then
  log "rustup toolchain with $TARGET"
  CARGO_TARGET_DIR="$TARGET_DIR" cargo build --release --target "$TARGET" -p voxstream-viewer "${LOCKED[@]}"
else
  if [ ! -x /usr/bin/rustc ] || [ ! -x /usr/bin/cargo ]; then
    die "no $TARGET toolchain: run 'rustup target add $TARGET', or bash scripts/setup.sh (Debian rustc-web route)"
  fi
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
# --- 4. vendored tus-js-client for the upload page ----------------------------------------------
# Its browser bundle (defines window.tus) and LICENSE, at the version and integrity that
# tests/browser/package-lock.json pins: from node_modules when scripts/setup.sh installed it there,
# else from the npm registry's tarball, checked against the lockfile's sha512 (the docker build has
# no npm).
LOCK="$ROOT/tests/browser/package-lock.json"
TUS_PKG="$ROOT/tests/browser/node_modules/tus-js-client"
TUS_BLOCK="$(grep -A3 '"node_modules/tus-js-client"' "$LOCK")"
TUS_WANT="$(printf '%s\n' "$TUS_BLOCK" | sed -n 's/.*"version": *"\([^"]*\)".*/\1/p')"
TUS_SRI="$(printf '%s\n' "$TUS_BLOCK" | sed -n 's/.*"integrity": *"sha512-\([^"]*\)".*/\1/p')"
if [ -z "$TUS_WANT" ] || [ -z "$TUS_SRI" ]; then die "tus-js-client's version or integrity is missing from $LOCK"; fi
TUS_HAVE=""
if [ -f "$TUS_PKG/package.json" ]; then
  TUS_HAVE="$(sed -n 's/^ *"version": *"\([^"]*\)".*/\1/p' "$TUS_PKG/package.json" | head -1)"
fi
if [ "$TUS_HAVE" != "$TUS_WANT" ]; then
  TUS_PKG="${CARGO_TARGET_DIR:-$ROOT/target}/vendor/tus-js-client-$TUS_WANT/package"
  if [ ! -f "$TUS_PKG/dist/tus.min.js" ]; then
    TGZ="$(dirname "$TUS_PKG").tgz"
    mkdir -p "$(dirname "$TUS_PKG")"
    log "downloading tus-js-client $TUS_WANT from the npm registry"
    curl -fsSL --retry 3 -o "$TGZ" "https://registry.npmjs.org/tus-js-client/-/tus-js-client-$TUS_WANT.tgz" ||
      die "cannot download tus-js-client $TUS_WANT (no network? run bash scripts/setup.sh to install it with npm)"
    GOT="$(openssl dgst -sha512 -binary "$TGZ" | base64 -w0)"
    [ "$GOT" = "$TUS_SRI" ] || die "tus-js-client-$TUS_WANT.tgz does not match the integrity in $LOCK"
    tar -xzf "$TGZ" -C "$(dirname "$TUS_PKG")" package/dist/tus.min.js package/LICENSE ||
      die "cannot unpack tus-js-client-$TUS_WANT.tgz"
  fi
fi
mkdir -p "$DIST/vendor"
for pair in "dist/tus.min.js:tus.min.js" "LICENSE:tus-js-client.LICENSE"; do
  src="$TUS_PKG/${pair%%:*}"
  dest="$DIST/vendor/${pair##*:}"
  [ -f "$src" ] || die "$src is missing from the tus-js-client package"
  cmp -s "$src" "$dest" 2>/dev/null || cp "$src" "$dest"
done

log "bundle ready: ${DIST#"$ROOT"/} ($(du -sh "$PKG/voxstream_viewer_bg.wasm" | cut -f1) wasm)"
