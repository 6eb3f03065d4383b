#!/usr/bin/env bash
# Install what voxstream's build and tests need, and nothing that is already there.
#
#   bash scripts/setup.sh
#
# Idempotent and quick (well under a second) when everything is present. Made for Debian
# bookworm (run as root, or as a user with sudo); on other systems it checks the tools and tells
# you what is missing instead of installing.
#
# What it makes sure of:
#   - a Rust toolchain with cargo, clippy and rustfmt (rustup's, or Debian's rust-web packages)
#   - a way to build wasm32-unknown-unknown: rustup's target if installed, else the Debian route
#     (rustc-web + cargo-web + rust-web-src for -Zbuild-std, lld-22 for wasm-ld)
#   - wasm-bindgen-cli 0.2.130 (matches the wasm-bindgen crate in Cargo.lock)
#   - chromium + chromium-driver (headless WebGPU on SwiftShader for the browser test)
#   - mesa-vulkan-drivers (lavapipe: Vulkan on the CPU for the native render test)
#   - node + npm, and tests/browser/node_modules (playwright-core, from package-lock.json)
#   - python3 + python3-venv, and the pinned Python tools venv of scripts/schemathesis.sh
#     (schemathesis, tuspy) in ~/.cache/voxstream-tools (quick when it is there)
#
# Environment: VOXSTREAM_SETUP_NO_INSTALL=1 only checks (exit 1 listing what is missing).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
WASM_BINDGEN_VERSION="0.2.130"
CARGO_HOME="${CARGO_HOME:-$HOME/.cargo}"
export PATH="$CARGO_HOME/bin:$PATH"

SCRIPT_NAME=setup
# shellcheck source=scripts/lib/preamble.sh
. "$(dirname "${BASH_SOURCE[0]}")/lib/preamble.sh"

NO_INSTALL="${VOXSTREAM_SETUP_NO_INSTALL:-0}"

# --- privilege for apt ---------------------------------------------------------------------
SUDO=()
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null 2>&1; then
    SUDO=(sudo)
  fi
fi

have_apt() { command -v apt-get >/dev/null 2>&1 && command -v dpkg-query >/dev/null 2>&1; }

pkg_installed() {
  [ "$(dpkg-query -W -f='${Status}' "$1" 2>/dev/null)" = "install ok installed" ]
}

APT_UPDATED=0
can_apt() {
  have_apt && [ "$NO_INSTALL" != "1" ] && { [ "$(id -u)" -eq 0 ] || [ "${#SUDO[@]}" -gt 0 ]; }
}
apt_update_once() {
  [ "$APT_UPDATED" -eq 0 ] || return 0
  log "apt-get update"
  "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -q >&2 || die "apt-get update failed"
  APT_UPDATED=1
}
apt_install() {
  # apt_install PKG... : installs the given packages (callers pass only missing ones).
  [ "$#" -gt 0 ] || return 0
  if [ "$NO_INSTALL" = "1" ]; then
    die "missing Debian packages: $* (VOXSTREAM_SETUP_NO_INSTALL=1, not installing)"
  fi
  have_apt || die "missing: $* — this is not a Debian/Ubuntu system with apt; install the equivalents by hand"
  if [ "$(id -u)" -ne 0 ] && [ "${#SUDO[@]}" -eq 0 ]; then
    die "missing Debian packages: $* — not root and sudo is unavailable; run: apt-get install $*"
  fi
  apt_update_once
  log "apt-get install $*"
  "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "$@" >&2 ||
    die "apt-get install $* failed"
}

missing_pkgs() {
  local p
  for p in "$@"; do pkg_installed "$p" || printf '%s\n' "$p"; done
}

apt_candidate() {
  # prints the candidate version of a package, empty if apt does not know it
  apt-cache policy "$1" 2>/dev/null | awk '/Candidate:/ { if ($2 != "(none)") print $2 }'
}

# --- 1. Rust toolchain -----------------------------------------------------------------------
WANT=()
RUSTUP_WASM=0
if command -v rustup >/dev/null 2>&1; then
  if rustup target list --installed 2>/dev/null | grep -qx 'wasm32-unknown-unknown'; then
    RUSTUP_WASM=1
  fi
fi

if ! command -v cargo >/dev/null 2>&1; then
  # No cargo at all: prefer rustup's stable toolchain (Debian ships a rustup package from trixie
  # on); on bookworm fall back to Debian's rust-web toolchain, which is new enough (1.85+).
  # Package lists may be empty (fresh container): refresh them before asking what apt offers.
  if can_apt && [ -z "$(apt_candidate cargo-web)" ] && [ -z "$(apt_candidate rustup)" ]; then
    apt_update_once
  fi
  if have_apt && [ -n "$(apt_candidate rustup)" ]; then
    mapfile -t miss < <(missing_pkgs rustup)
    apt_install "${miss[@]}"
    log "rustup toolchain install stable (with clippy, rustfmt)"
    rustup toolchain install stable --profile minimal --component clippy,rustfmt >&2 ||
      die "rustup could not install the stable toolchain (no network to static.rust-lang.org?)"
    rustup default stable >&2
  elif have_apt && [ -n "$(apt_candidate cargo-web)" ]; then
    log "no cargo and no Debian rustup package: using Debian's rust-web toolchain"
    WANT+=(rustc-web cargo-web rust-web-clippy rustfmt-web)
  else
    die "no Rust toolchain: cargo is not on PATH and neither Debian's rustup nor cargo-web package is available.
       Install rustup from https://rustup.rs (then: rustup component add clippy rustfmt) and re-run."
  fi
fi

# If the only cargo is Debian's rust-web one, clippy and rustfmt come from Debian too.
if ! command -v rustup >/dev/null 2>&1 && have_apt && pkg_installed cargo-web; then
  WANT+=(rust-web-clippy rustfmt-web)
fi

# --- 2. wasm32 route --------------------------------------------------------------------------
if [ "$RUSTUP_WASM" -eq 0 ]; then
  if have_apt; then
    WANT+=(rustc-web cargo-web rust-web-src lld-22)
  else
    die "no wasm32-unknown-unknown target: run 'rustup target add wasm32-unknown-unknown'"
  fi
fi

# --- 3. browser, Vulkan on the CPU, node -----------------------------------------------------
if have_apt; then
  # ca-certificates: cargo/npm fetch over HTTPS; gcc + libc6-dev: the linker for host builds.
  WANT+=(ca-certificates gcc libc6-dev chromium chromium-driver mesa-vulkan-drivers)
  # python3-venv: `python3 -m venv` for the schemathesis/tuspy tools venv (scripts/schemathesis.sh).
  WANT+=(python3 python3-venv)
  if ! command -v node >/dev/null 2>&1; then
    WANT+=(nodejs)
    command -v npm >/dev/null 2>&1 || WANT+=(npm)
  elif ! command -v npm >/dev/null 2>&1; then
    WANT+=(npm)
  fi
  # dedupe and install what is missing
  mapfile -t WANT < <(printf '%s\n' "${WANT[@]}" | awk 'NF && !seen[$0]++')
  mapfile -t MISSING < <(missing_pkgs "${WANT[@]}")
  apt_install "${MISSING[@]}"
else
  for tool in chromium node npm python3; do
    command -v "$tool" >/dev/null 2>&1 || die "$tool is missing and this system has no apt; install it by hand"
  done
fi

command -v cargo >/dev/null 2>&1 || die "cargo is still not on PATH after installing the toolchain"
# The workspace needs Rust >= 1.87 (edition 2024, rust-version in Cargo.toml). Debian's plain
# rustc/cargo packages on bookworm are 1.63: too old.
rustc_minor="$(rustc --version 2>/dev/null | awk '{split($2, v, "."); print v[2] + 0}')"
if [ "${rustc_minor:-0}" -lt 87 ]; then
  die "$(rustc --version 2>/dev/null || echo 'rustc: missing') at $(command -v rustc || echo '?') is too old (need >= 1.87).
       Use rustup (rustup update stable) or Debian's rustc-web/cargo-web packages instead of rustc/cargo."
fi
cargo clippy --version >/dev/null 2>&1 || die "cargo clippy is unavailable (rustup component add clippy)"
cargo fmt --version >/dev/null 2>&1 || die "cargo fmt is unavailable (rustup component add rustfmt)"
if [ "$RUSTUP_WASM" -eq 0 ]; then
  [ -x /usr/lib/llvm-22/bin/wasm-ld ] || die "/usr/lib/llvm-22/bin/wasm-ld missing although lld-22 is installed"
  [ -d /usr/lib/rustlib/src/rust/library ] || die "rust-web-src is installed but /usr/lib/rustlib/src/rust/library is missing"
fi

# --- 4. wasm-bindgen-cli -----------------------------------------------------------------------
wb_version() { wasm-bindgen --version 2>/dev/null | awk '{print $2}'; }
if [ "$(wb_version)" != "$WASM_BINDGEN_VERSION" ]; then
  [ "$NO_INSTALL" = "1" ] && die "wasm-bindgen $WASM_BINDGEN_VERSION missing (found '$(wb_version)')"
  log "cargo install wasm-bindgen-cli --version $WASM_BINDGEN_VERSION (a few minutes)"
  # Not --locked: the lockfile published with 0.2.130 pins a yanked webpki-roots and fails.
  cargo install wasm-bindgen-cli --version "$WASM_BINDGEN_VERSION" --force >&2 ||
    die "cargo install wasm-bindgen-cli $WASM_BINDGEN_VERSION failed"
  [ "$(wb_version)" = "$WASM_BINDGEN_VERSION" ] ||
    die "wasm-bindgen on PATH is '$(wb_version)' (at $(command -v wasm-bindgen || echo none)), want $WASM_BINDGEN_VERSION; put $CARGO_HOME/bin first on PATH"
fi

# --- 5. node modules for the browser harness ---------------------------------------------------
BROWSER_DIR="$ROOT/tests/browser"
LOCK="$BROWSER_DIR/package-lock.json"
STAMP="$BROWSER_DIR/node_modules/.voxstream-lock.sha256"
[ -f "$LOCK" ] || die "$LOCK missing (it is committed; is the checkout complete?)"
lock_sum="$(sha256sum "$LOCK" | awk '{print $1}')"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$lock_sum" ] ||
  [ ! -f "$BROWSER_DIR/node_modules/playwright-core/package.json" ]; then
  [ "$NO_INSTALL" = "1" ] && die "tests/browser/node_modules is missing or stale (npm ci)"
  log "npm ci in tests/browser (playwright-core; no browser download)"
  (cd "$BROWSER_DIR" && PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1 npm ci --no-audit --no-fund >&2) ||
    die "npm ci in tests/browser failed"
  printf '%s\n' "$lock_sum" >"$STAMP"
fi

# --- 6. Python tools: schemathesis (API contract) and tuspy (tus client test) ---------------------
if [ "$NO_INSTALL" = "1" ]; then
  VOXSTREAM_TOOLS_VENV="$(bash "$ROOT/scripts/schemathesis.sh" --check 2>/dev/null)" ||
    die "the Python tools venv of scripts/schemathesis.sh is missing (bash scripts/schemathesis.sh --install)"
else
  VOXSTREAM_TOOLS_VENV="$(bash "$ROOT/scripts/schemathesis.sh" --venv)" ||
    die "installing the Python tools (scripts/schemathesis.sh --install) failed"
fi

log "ok ($(cargo --version), wasm route: $([ "$RUSTUP_WASM" -eq 1 ] && echo rustup || echo debian), wasm-bindgen $(wb_version), node $(node --version), python tools $VOXSTREAM_TOOLS_VENV)"
