#!/usr/bin/env bash
# Build docker/Dockerfile with buildah on a machine that has no Docker engine and cannot reach
# a container registry (only the Debian mirror and crates.io), then smoke-test the image.
#
#   bash docker/buildah-local.sh            (Debian bookworm, root; opt-in, slow: ~a full release build)
#
# 1. debootstrap a bookworm minbase rootfs   -> localhost/voxstream-base/debian:bookworm
#    (stands in for debian:bookworm-slim, the default RUNTIME_IMAGE)
# 2. that + build-essential + Debian's wasm route (rustc-web, rust-web-src, lld-22) + this host's
#    rustup stable toolchain and wasm-bindgen copied in -> localhost/voxstream-base/rust:bookworm
#    (stands in for rust:1.95-bookworm; rustup here cannot download the wasm32 target, so the image
#    is built with RUSTUP_WASM_TARGET=0 and scripts/build-web.sh takes the Debian route)
# 3. buildah bud docker/Dockerfile -> localhost/voxstream:dev
# 4. smoke test: run the image's entrypoint with an empty store volume on 127.0.0.1:$SMOKE_PORT,
#    wait for it to build the default scan, then GET /api/scenes, / and one block.
#
# Environment: VX_BUILDAH_WORK (default /var/tmp/voxstream-buildah), SMOKE_PORT (default 18080),
# BASES_ONLY=1 (stop after step 2), SKIP_BUILD=1 (smoke-test the existing image), SKIP_SMOKE=1,
# REBUILD_BASES=1.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
WORK="${VX_BUILDAH_WORK:-/var/tmp/voxstream-buildah}"
SMOKE_PORT="${SMOKE_PORT:-18080}"
B=(buildah --storage-driver vfs)
RUNTIME_BASE=localhost/voxstream-base/debian:bookworm
BUILDER_BASE=localhost/voxstream-base/rust:bookworm
IMAGE=localhost/voxstream:dev
MIRROR=http://deb.debian.org/debian

SCRIPT_NAME=buildah-local
# shellcheck source=scripts/lib/preamble.sh
. "$(dirname "${BASH_SOURCE[0]}")/../scripts/lib/preamble.sh"
log() { printf '\n=== buildah-local: %s\n' "$*" >&2; }

[ "$(id -u)" -eq 0 ] || die "run as root (buildah with vfs storage and chroot isolation)"
for tool in buildah debootstrap curl; do
  command -v "$tool" >/dev/null 2>&1 || die "$tool missing: apt-get install buildah debootstrap curl"
done
mkdir -p "$WORK"

have_image() { "${B[@]}" inspect --type image "$1" >/dev/null 2>&1; }
if [ "${REBUILD_BASES:-0}" = 1 ]; then
  "${B[@]}" rmi -f "$IMAGE" "$BUILDER_BASE" "$RUNTIME_BASE" >/dev/null 2>&1 || true
fi

# --- 1. runtime base ---------------------------------------------------------------------------
ROOTFS="$WORK/rootfs-bookworm"
if ! have_image "$RUNTIME_BASE"; then
  if [ ! -x "$ROOTFS/bin/bash" ]; then
    log "debootstrap --variant=minbase bookworm"
    rm -rf "$ROOTFS"
    debootstrap --variant=minbase bookworm "$ROOTFS" "$MIRROR" >"$WORK/debootstrap.log" 2>&1 ||
      die "debootstrap failed; see $WORK/debootstrap.log"
  fi
  log "making $RUNTIME_BASE"
  ctr="$("${B[@]}" from scratch)"
  mnt="$("${B[@]}" mount "$ctr")"
  cp -a "$ROOTFS/." "$mnt/"
  cat >"$mnt/etc/apt/sources.list" <<EOF
deb $MIRROR bookworm main
deb $MIRROR bookworm-updates main
deb http://deb.debian.org/debian-security bookworm-security main
EOF
  rm -rf "$mnt"/var/lib/apt/lists/* "$mnt"/var/cache/apt/archives/*.deb
  "${B[@]}" umount "$ctr" >/dev/null
  "${B[@]}" config --env PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    --cmd /bin/bash --label org.opencontainers.image.description="debootstrap bookworm minbase" "$ctr"
  "${B[@]}" commit -q "$ctr" "$RUNTIME_BASE" >/dev/null
  "${B[@]}" rm "$ctr" >/dev/null
fi

# --- 2. builder base ---------------------------------------------------------------------------
if ! have_image "$BUILDER_BASE"; then
  command -v rustup >/dev/null 2>&1 || die "this host has no rustup toolchain to copy into the builder image"
  toolchain="$(rustup show active-toolchain | awk '{print $1}')"
  tc_dir="$(rustup run "$toolchain" rustc --print sysroot)"
  [ -d "$tc_dir/lib/rustlib" ] || die "cannot find the toolchain directory ($tc_dir)"
  log "making $BUILDER_BASE (toolchain $toolchain from $tc_dir)"
  ctr="$("${B[@]}" from "$RUNTIME_BASE")"
  "${B[@]}" run --isolation chroot "$ctr" -- sh -c '
    set -e
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -q
    apt-get install -y -q --no-install-recommends build-essential ca-certificates pkg-config git curl \
      rustc-web cargo-web rust-web-src lld-22
    rm -rf /var/lib/apt/lists/*' >&2
  mnt="$("${B[@]}" mount "$ctr")"
  # Trust the same extra CAs as this host (an egress proxy may re-sign crates.io's certificate).
  if compgen -G "/usr/local/share/ca-certificates/*.crt" >/dev/null; then
    cp /usr/local/share/ca-certificates/*.crt "$mnt/usr/local/share/ca-certificates/"
    "${B[@]}" run --isolation chroot "$ctr" -- update-ca-certificates >&2
  fi
  mkdir -p "$mnt/usr/local/rustup/toolchains/stable-x86_64-unknown-linux-gnu" "$mnt/usr/local/cargo/bin"
  # The toolchain without its HTML docs (share/doc is most of its size).
  tar -C "$tc_dir" --exclude=./share/doc -cf - . |
    tar -C "$mnt/usr/local/rustup/toolchains/stable-x86_64-unknown-linux-gnu" -xf -
  printf 'version = "12"\ndefault_toolchain = "stable-x86_64-unknown-linux-gnu"\n' \
    >"$mnt/usr/local/rustup/settings.toml"
  cp "$(command -v rustup)" "$mnt/usr/local/cargo/bin/rustup"
  for proxy in cargo rustc rustdoc cargo-clippy clippy-driver cargo-fmt rustfmt; do
    ln -sf rustup "$mnt/usr/local/cargo/bin/$proxy"
  done
  if [ "$(wasm-bindgen --version 2>/dev/null)" = "wasm-bindgen 0.2.130" ]; then
    cp "$(command -v wasm-bindgen)" "$mnt/usr/local/cargo/bin/"
  fi
  "${B[@]}" umount "$ctr" >/dev/null
  "${B[@]}" config --env RUSTUP_HOME=/usr/local/rustup --env CARGO_HOME=/usr/local/cargo \
    --env PATH=/usr/local/cargo/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    --label org.opencontainers.image.description="bookworm + host rustup toolchain + Debian wasm route" "$ctr"
  "${B[@]}" run --isolation chroot "$ctr" -- sh -c 'cargo --version && rustc --version && (wasm-bindgen --version || true)' >&2
  "${B[@]}" commit -q "$ctr" "$BUILDER_BASE" >/dev/null
  "${B[@]}" rm "$ctr" >/dev/null
fi

[ "${BASES_ONLY:-0}" = 1 ] && exit 0

# --- 3. the image --------------------------------------------------------------------------------
if [ "${SKIP_BUILD:-0}" = 1 ]; then
  have_image "$IMAGE" || die "SKIP_BUILD=1 but $IMAGE does not exist"
else
  log "buildah bud docker/Dockerfile -> $IMAGE"
  start=$SECONDS
  # --format docker: the OCI format drops SHELL and HEALTHCHECK, which Docker keeps.
  "${B[@]}" bud --isolation chroot --layers --format docker \
    --build-arg BUILDER_IMAGE="$BUILDER_BASE" \
    --build-arg RUNTIME_IMAGE="$RUNTIME_BASE" \
    --build-arg RUSTUP_WASM_TARGET=0 \
    -f "$ROOT/docker/Dockerfile" -t "$IMAGE" "$ROOT" >&2 || die "buildah bud failed"
  echo "buildah-local: built $IMAGE in $((SECONDS - start))s" >&2
fi
"${B[@]}" inspect --type image --format '{{.OCIv1.Config.User}} {{.OCIv1.Config.Entrypoint}} {{.OCIv1.Config.ExposedPorts}} {{.OCIv1.Config.Volumes}}' "$IMAGE" >&2

[ "${SKIP_SMOKE:-0}" = 1 ] && exit 0

# --- 4. smoke test -------------------------------------------------------------------------------
# buildah 1.28's `run` gives an image-declared VOLUME its own anonymous volume even when -v names
# the same path, so the host directory is mounted at /smoke-store and VOXSTREAM_STORE points there
# (the entrypoint's knob). Under Docker/Podman, `-v NAME:/store` is the normal way.
log "smoke test: entrypoint with an empty store on 127.0.0.1:$SMOKE_PORT"
STORE_VOL="$WORK/smoke-store"
rm -rf "$STORE_VOL"
mkdir -p "$STORE_VOL"
chown 10001:10001 "$STORE_VOL"
ctr="$("${B[@]}" from "$IMAGE")"
run_pid=""
cleanup() {
  if [ -n "$run_pid" ]; then
    kill "$run_pid" 2>/dev/null || true
    wait "$run_pid" 2>/dev/null || true
  fi
  "${B[@]}" rm "$ctr" >/dev/null 2>&1 || true
}
trap cleanup EXIT
URL="http://127.0.0.1:$SMOKE_PORT"
# chroot isolation shares the host network; the image's user, env and entrypoint apply.
"${B[@]}" run --isolation chroot -v "$STORE_VOL:/smoke-store" \
  --env VOXSTREAM_STORE=/smoke-store --env VOXSTREAM_ADDR="127.0.0.1:$SMOKE_PORT" \
  "$ctr" -- /usr/local/bin/voxstream-entrypoint >"$WORK/smoke.log" 2>&1 &
run_pid=$!
for _ in $(seq 1 600); do
  curl -fsS "$URL/api/scenes" >"$WORK/scenes.json" 2>/dev/null && break
  kill -0 "$run_pid" 2>/dev/null || die "the container exited early; $WORK/smoke.log:
$(tail -40 "$WORK/smoke.log")"
  sleep 1
done
curl -fsS "$URL/api/scenes" >"$WORK/scenes.json" || die "server never answered; see $WORK/smoke.log"
grep -Eq '"id": *"koala"' "$WORK/scenes.json" || die "/api/scenes has no koala scene: $(cat "$WORK/scenes.json")"
curl -fsS "$URL/" >"$WORK/index.html" || die "GET / failed"
grep -qi 'voxstream-canvas' "$WORK/index.html" || die "GET / did not return the viewer page"
curl -fsS "$URL/api/scenes/koala/manifest" >"$WORK/manifest.json" || die "GET manifest failed"
key="$(grep -Eo '"key": *"[0-9]+-[0-9]+-[0-9]+-[0-9]+"' "$WORK/manifest.json" | head -n1 | cut -d'"' -f4 || true)"
[ -n "$key" ] || die "no block key in the manifest"
curl -fsS "$URL/api/scenes/koala/blocks/$key" -o "$WORK/block.vxb" || die "GET block $key failed"
# format::codec::BLOCK_MAGIC
[ "$(head -c4 "$WORK/block.vxb")" = VXB2 ] || die "block $key does not start with the VXB2 magic"
# Blocks live in packs (one byte range each): the served bytes must be a range of a pack on the volume.
python3 - "$WORK/block.vxb" "$STORE_VOL"/koala/packs/*.vxp <<'PY' || die "served block $key is in no pack of the mounted store"
import sys
block = open(sys.argv[1], "rb").read()
sys.exit(0 if any(block in open(p, "rb").read() for p in sys.argv[2:]) else 1)
PY
[ "$(stat -c %u "$STORE_VOL/koala/manifest.json")" = 10001 ] || die "store files are not owned by the image's user (10001)"
wasm="$(grep -o 'pkg/[A-Za-z0-9_.-]*\.js' "$WORK/index.html" | head -n1 || true)"
if [ -n "$wasm" ]; then
  curl -fsS "$URL/$wasm" -o /dev/null || die "GET /$wasm failed"
fi
curl -fsS "$URL/pkg/voxstream_viewer_bg.wasm" -o "$WORK/viewer.wasm" || die "GET the wasm module failed"
[ "$(head -c4 "$WORK/viewer.wasm" | od -An -tx1 | tr -d ' ')" = 0061736d ] || die "the served wasm module has no wasm magic"
# The image's HEALTHCHECK command, run in a second container of the same image (host network),
# pointed at the smoke port.
hc="$("${B[@]}" inspect --type image "$IMAGE" |
  python3 -c 'import json,sys; t=json.load(sys.stdin)["Docker"]["config"]["Healthcheck"]["Test"]; assert t[0]=="CMD"; print(t[3])')"
hc_ctr="$("${B[@]}" from "$IMAGE")"
hc_ok=0
"${B[@]}" run --isolation chroot "$hc_ctr" -- bash -c "${hc//8080/$SMOKE_PORT}" && hc_ok=1
"${B[@]}" rm "$hc_ctr" >/dev/null
[ "$hc_ok" = 1 ] || die "the image's HEALTHCHECK command failed against the running server"
echo "buildah-local: smoke test passed: $(head -c 200 "$WORK/scenes.json"); block $key served from the mounted store" >&2
