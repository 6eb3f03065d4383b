#!/usr/bin/env bash
# Install Garage (crates.io `garage`, an S3-compatible distributed object store) into a tools
# folder outside the clone, keyed by version, and print the binary's path on stdout:
#
#   GARAGE="$(bash scripts/garage.sh)"
#
# Idempotent: when <tools>/garage-<version>/bin/garage exists and answers `--version`, nothing is
# compiled (well under a second). A cold install compiles Garage with `cargo install --locked`
# (measured on 2 shared cores: about 8.5 minutes, a 55 MB binary). The cluster script and the
# tests use it; voxstream itself never links Garage, it only speaks S3 to it.
#
# Environment:
#   VOXSTREAM_TOOLS_DIR  where tools are kept (default ${XDG_CACHE_HOME:-$HOME/.cache}/voxstream-tools)
#   GARAGE_VERSION       the pinned version (default below; the one the tests were run against)
#   GARAGE_JOBS          cargo -j for the compile (default: cargo's own)
set -euo pipefail

GARAGE_VERSION="${GARAGE_VERSION:-2.5.0}"
TOOLS="${VOXSTREAM_TOOLS_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/voxstream-tools}"
DEST="$TOOLS/garage-$GARAGE_VERSION"
BIN="$DEST/bin/garage"
CARGO_HOME="${CARGO_HOME:-$HOME/.cargo}"
export PATH="$CARGO_HOME/bin:$PATH"

SCRIPT_NAME=garage.sh
# shellcheck source=scripts/lib/preamble.sh
. "$(dirname "${BASH_SOURCE[0]}")/lib/preamble.sh"

if [ -x "$BIN" ] && "$BIN" --version >/dev/null 2>&1; then
  printf '%s\n' "$BIN"
  exit 0
fi

command -v cargo >/dev/null 2>&1 || die "cargo is missing (bash scripts/setup.sh installs a Rust toolchain)"
mkdir -p "$TOOLS"
# Tests start in parallel and each asks for Garage: one compiles, the others wait for it here and
# then find the binary, instead of compiling it again.
exec 9>"$TOOLS/garage-$GARAGE_VERSION.lock"
flock 9 || die "cannot lock $TOOLS/garage-$GARAGE_VERSION.lock"
if [ -x "$BIN" ] && "$BIN" --version >/dev/null 2>&1; then
  printf '%s\n' "$BIN"
  exit 0
fi
# A half-finished install (killed compile) never leaves a binary at $BIN: cargo installs into a
# temporary root that is renamed into place only when the compile succeeded.
TMP="$DEST.partial.$$"
rm -rf "$TMP"
trap 'rm -rf "$TMP"' EXIT
JOBS=()
[ -n "${GARAGE_JOBS:-}" ] && JOBS=(-j "$GARAGE_JOBS")
log "cargo install --locked garage $GARAGE_VERSION into $DEST (a cold compile takes about 9 minutes on 2 cores)"
start=$SECONDS
# A target dir of its own, so repeated attempts reuse what compiled.
CARGO_TARGET_DIR="$TOOLS/garage-build-target" cargo install --locked --version "$GARAGE_VERSION" garage \
  --root "$TMP" "${JOBS[@]}" >&2 || die "cargo install garage $GARAGE_VERSION failed (see above)"
[ -x "$TMP/bin/garage" ] || die "cargo install finished but $TMP/bin/garage is missing"
rm -rf "$DEST"
mv "$TMP" "$DEST"
rm -rf "$TOOLS/garage-build-target"
log "installed $("$BIN" --version 2>/dev/null | head -1) in $((SECONDS - start)) s"
printf '%s\n' "$BIN"
