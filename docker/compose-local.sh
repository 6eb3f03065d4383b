#!/usr/bin/env bash
# Run docker/compose.yaml for real on a machine with no Docker engine and no registry access
# (only the Debian mirror, PyPI and crates.io), with podman and podman-compose, and check the
# deployment it makes from the outside:
#
#   bash docker/compose-local.sh            (Debian bookworm, root; opt-in, slow the first time:
#                                            docker/buildah-local.sh builds the voxstream image)
#
# 1. Images. localhost/voxstream:dev from docker/buildah-local.sh. The compose file names three
#    registry images; each gets a local stand-in under the same name, built on the debootstrap
#    bookworm base (tagged debian:bookworm-slim):
#      dxflrs/garage:v2.5.0                   the Garage binary of scripts/garage.sh at /garage
#                                             (the official image is that binary alone)
#      postgres:15-bookworm                   Debian's postgresql-15 and an entrypoint doing what
#                                             the official one does with POSTGRES_USER/_DB/_PASSWORD
#      nginxinc/nginx-unprivileged:1.27-alpine Debian's nginx as uid 101, plus wget
#    docker/garage.Dockerfile is then built as the compose file says.
# 2. Up, in the order the compose file's depends_on conditions state: the Garage nodes healthy,
#    garage-init exited 0, postgres healthy, both replicas healthy, nginx healthy. podman 4.3 (Debian
#    12) does not run health checks without systemd and podman-compose ignores health conditions
#    before podman 4.6, so this script runs each container's own health check (`podman healthcheck
#    run`) every 2 s and waits on the conditions itself.
# 3. Checks through nginx at http://127.0.0.1:8080 (the compose file's published port):
#    the viewer at /, the documented `compose run --rm replica-1 build` into the bucket, the scene
#    listed, its manifest and a block (VXB2, served by either replica), an upload with the token
#    built once by the replicas, a replica killed (block GETs keep answering 200) and started again,
#    a Garage node killed (reads and a build keep working), then `down -v`.
#
# Environment: VX_COMPOSE_WORK (default /var/tmp/voxstream-compose), KEEP_UP=1 (leave it running),
# STANDINS_ONLY=1 (stop after the stand-in images).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
WORK="${VX_COMPOSE_WORK:-/var/tmp/voxstream-compose}"
PROJECT=voxstream
URL=http://127.0.0.1:8080
BASE=localhost/voxstream-base/debian:bookworm
SCRIPT_NAME=compose-local
# shellcheck source=scripts/lib/preamble.sh
. "$ROOT/scripts/lib/preamble.sh"
log() { printf '\n=== compose-local: %s\n' "$*" >&2; }

[ "$(id -u)" -eq 0 ] || die "run as root (rootful podman with vfs storage)"
mkdir -p "$WORK"
export DEBIAN_FRONTEND=noninteractive
missing=()
for pkg in podman buildah debootstrap netavark aardvark-dns iptables catatonit curl; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if [ "${#missing[@]}" -gt 0 ]; then
  log "apt-get install ${missing[*]}"
  apt-get install -y -q "${missing[@]}" >"$WORK/apt.log" 2>&1 || die "apt-get failed; see $WORK/apt.log"
fi
PC_VENV="$WORK/podman-compose"
if [ ! -x "$PC_VENV/bin/podman-compose" ]; then
  python3 -m venv "$PC_VENV"
  "$PC_VENV/bin/pip" install -q --disable-pip-version-check "podman-compose==1.6.0" ||
    die "cannot install podman-compose from PyPI"
fi

# The same image store as docker/buildah-local.sh (buildah --storage-driver vfs).
cat >"$WORK/storage.conf" <<'EOF'
[storage]
driver = "vfs"
runroot = "/run/containers/storage"
graphroot = "/var/lib/containers/storage"
EOF
export CONTAINERS_STORAGE_CONF="$WORK/storage.conf"
B=(buildah --storage-driver vfs)

# --- podman on this machine -------------------------------------------------------------------
# Inside an unprivileged-ish container (no CAP_SYS_RESOURCE, cgroup v1 with a cgroup2 'unified'
# mount beside it) crun can neither set the spec's rlimits nor handle hybrid cgroups. Then podman
# runs without cgroups, through a crun that drops rlimits and cgroup mounts from the spec, in a
# mount namespace without the cgroup2 mount (one namespace for every podman call, because podman
# keeps network namespaces as bind mounts there).
PODMAN=("$(command -v podman)")
HOLDER=""
probe() { "${PODMAN[@]}" run --rm --network none "$BASE" true >"$WORK/probe.log" 2>&1; }
cleanup_holder() { [ -z "$HOLDER" ] || kill "$HOLDER" 2>/dev/null || true; }
trap cleanup_holder EXIT
"${B[@]}" inspect --type image "$BASE" >/dev/null 2>&1 || BASES_ONLY=1 bash "$ROOT/docker/buildah-local.sh" ||
  die "cannot make the base images (docker/buildah-local.sh)"
if ! probe; then
  log "plain podman cannot run a container here ($(tail -n1 "$WORK/probe.log")); using the sandbox shim"
  mkdir -p "$WORK/shim"
  cat >"$WORK/shim/crun" <<'EOF'
#!/bin/bash
# crun without the spec's rlimits, cgroup mounts and cgroup resources (create/run: --bundle;
# exec: --process).
args=("$@"); files=()
for ((i = 0; i < ${#args[@]}; i++)); do
  case "${args[$i]}" in
    --bundle | -b) files+=("${args[$((i + 1))]}/config.json") ;;
    --process | -p) files+=("${args[$((i + 1))]}") ;;
    --bundle=*) files+=("${args[$i]#--bundle=}/config.json") ;;
    --process=*) files+=("${args[$i]#--process=}") ;;
  esac
done
for f in "${files[@]}"; do
  [ -f "$f" ] || continue
  python3 - "$f" <<'PY'
import json, sys
p = sys.argv[1]
d = json.load(open(p))
d.get("process", d).pop("rlimits", None)
if "mounts" in d:
    d["mounts"] = [m for m in d["mounts"] if m.get("type") not in ("cgroup", "cgroup2")]
d.get("linux", {}).pop("cgroupsPath", None)
d.get("linux", {}).pop("resources", None)
json.dump(d, open(p, "w"))
PY
done
exec /usr/bin/crun "$@"
EOF
  chmod +x "$WORK/shim/crun"
  cat >"$WORK/containers.conf" <<EOF
[containers]
cgroups = "disabled"
[engine]
cgroup_manager = "cgroupfs"
runtime = "crun"
[engine.runtimes]
crun = ["$WORK/shim/crun"]
EOF
  export CONTAINERS_CONF="$WORK/containers.conf"
  if mountpoint -q /sys/fs/cgroup/unified 2>/dev/null; then
    unshare -m --propagation private bash -c 'umount /sys/fs/cgroup/unified && exec sleep infinity' &
    HOLDER=$!
    sleep 0.5
    PODMAN=(nsenter -t "$HOLDER" -m -- "${PODMAN[0]}")
  fi
  probe || die "podman cannot run a container even with the shim: $(tail -n3 "$WORK/probe.log")"
fi
pm() { "${PODMAN[@]}" "$@"; }

# --- 1. images --------------------------------------------------------------------------------
have() { "${B[@]}" inspect --type image "$1" >/dev/null 2>&1; }
"${B[@]}" tag "$BASE" docker.io/library/debian:bookworm-slim
bud() { # bud NAME DIR: build DIR/Containerfile as NAME with no registry access
  "${B[@]}" bud --isolation chroot --pull=never --format docker -t "$1" -f "$2/Containerfile" "$2" \
    >"$WORK/bud-$(basename "$2").log" 2>&1 || die "building $1 failed; see $WORK/bud-$(basename "$2").log"
}
if ! have docker.io/dxflrs/garage:v2.5.0; then
  log "stand-in dxflrs/garage:v2.5.0"
  mkdir -p "$WORK/garage-image"
  cp "$(bash "$ROOT/scripts/garage.sh")" "$WORK/garage-image/garage"
  printf 'FROM scratch\nCOPY garage /garage\n' >"$WORK/garage-image/Containerfile"
  bud docker.io/dxflrs/garage:v2.5.0 "$WORK/garage-image"
fi
if ! have docker.io/library/postgres:15-bookworm; then
  log "stand-in postgres:15-bookworm"
  mkdir -p "$WORK/postgres-image"
  cat >"$WORK/postgres-image/docker-entrypoint.sh" <<'EOF'
#!/bin/sh
# What the official image's entrypoint does with an empty PGDATA: initdb with POSTGRES_USER as
# superuser and POSTGRES_PASSWORD, password logins from the network, create POSTGRES_DB.
set -eu
: "${POSTGRES_PASSWORD:?}"
user="${POSTGRES_USER:-postgres}"
db="${POSTGRES_DB:-$user}"
if [ ! -s "$PGDATA/PG_VERSION" ]; then
  pw="$(mktemp)"
  printf '%s' "$POSTGRES_PASSWORD" >"$pw"
  initdb -D "$PGDATA" --username="$user" --pwfile="$pw" --auth-local=trust --auth-host=scram-sha-256 >/dev/null
  rm -f "$pw"
  echo "listen_addresses = '*'" >>"$PGDATA/postgresql.conf"
  echo "host all all all scram-sha-256" >>"$PGDATA/pg_hba.conf"
  pg_ctl -D "$PGDATA" -o "-c listen_addresses=''" -w start >/dev/null
  [ "$db" = postgres ] || createdb -U "$user" "$db"
  pg_ctl -D "$PGDATA" -m fast -w stop >/dev/null
fi
exec "$@"
EOF
  cat >"$WORK/postgres-image/Containerfile" <<'EOF'
FROM docker.io/library/debian:bookworm-slim
RUN apt-get update -q && apt-get install -y -q --no-install-recommends postgresql-15 \
 && rm -rf /var/lib/apt/lists/* \
 && mkdir -p /var/lib/postgresql/data /var/run/postgresql \
 && chown -R postgres:postgres /var/lib/postgresql /var/run/postgresql
ENV PATH=/usr/lib/postgresql/15/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    PGDATA=/var/lib/postgresql/data
COPY --chmod=0755 docker-entrypoint.sh /usr/local/bin/docker-entrypoint.sh
ENTRYPOINT ["/usr/local/bin/docker-entrypoint.sh"]
CMD ["postgres"]
EOF
  bud docker.io/library/postgres:15-bookworm "$WORK/postgres-image"
fi
if ! have docker.io/nginxinc/nginx-unprivileged:1.27-alpine; then
  log "stand-in nginxinc/nginx-unprivileged:1.27-alpine"
  mkdir -p "$WORK/nginx-image"
  cat >"$WORK/nginx-image/Containerfile" <<'EOF'
FROM docker.io/library/debian:bookworm-slim
RUN apt-get update -q && apt-get install -y -q --no-install-recommends nginx-light wget \
 && rm -rf /var/lib/apt/lists/* \
 && groupadd --system --gid 101 nginx && useradd --system --uid 101 --gid nginx --no-create-home nginx \
 && mkdir -p /var/log/nginx /var/lib/nginx && chown -R 101:101 /var/log/nginx /var/lib/nginx
USER 101
EXPOSE 8080
CMD ["nginx", "-g", "daemon off;"]
EOF
  bud docker.io/nginxinc/nginx-unprivileged:1.27-alpine "$WORK/nginx-image"
fi

[ "${STANDINS_ONLY:-0}" = 1 ] && exit 0
have localhost/voxstream:dev || SKIP_SMOKE=1 bash "$ROOT/docker/buildah-local.sh" ||
  die "cannot build localhost/voxstream:dev (docker/buildah-local.sh)"

# --- 2. up ------------------------------------------------------------------------------------
rand() { od -An -tx1 -N"$1" /dev/urandom | tr -d ' \n'; }
ENV_FILE="$WORK/compose.env"
cat >"$ENV_FILE" <<EOF
GARAGE_RPC_SECRET=$(rand 32)
GARAGE_KEY_ID=GK$(rand 12)
GARAGE_SECRET_KEY=$(rand 32)
POSTGRES_PASSWORD=$(rand 24)
VOXSTREAM_TOKEN=$(rand 24)
VOXSTREAM_LEASE_SECS=10
EOF
TOKEN="$(sed -n 's/^VOXSTREAM_TOKEN=//p' "$ENV_FILE")"
# podman-compose calls `podman` from PATH: point it at this machine's way of running podman.
mkdir -p "$WORK/bin"
printf '#!/bin/sh\nexec %s "$@"\n' "${PODMAN[*]}" >"$WORK/bin/podman"
chmod +x "$WORK/bin/podman"
pc() {
  PATH="$WORK/bin:$PATH" "$PC_VENV/bin/podman-compose" -p "$PROJECT" --env-file "$ENV_FILE" \
    -f "$ROOT/docker/compose.yaml" "$@"
}
ctr() { echo "${PROJECT}_$1_1"; }
health_loop() {
  while sleep 2; do
    for c in $(pm ps --format '{{.Names}}' 2>/dev/null); do
      pm healthcheck run "$c" >/dev/null 2>&1 || true
    done
  done
}
down() {
  [ "${KEEP_UP:-0}" = 1 ] && return 0
  pc down -v >"$WORK/down.log" 2>&1 || true
}
health_pid=""
finish() {
  [ -z "$health_pid" ] || kill "$health_pid" 2>/dev/null || true
  down
  cleanup_holder
}
trap finish EXIT

log "compose down -v (a previous run), build docker/garage.Dockerfile"
pc down -v >"$WORK/down.log" 2>&1 || true
t0=$SECONDS
pc build garage-1 >"$WORK/build.log" 2>&1 || die "compose build failed; see $WORK/build.log"
health_loop &
health_pid=$!
status() { pm inspect --format "$1" "$(ctr "$2")" 2>/dev/null || true; }
wait_healthy() {
  for s in "$@"; do
    for _ in $(seq 1 180); do
      [ "$(status '{{.State.Health.Status}}' "$s")" = healthy ] && continue 2
      sleep 1
    done
    pm logs --tail 30 "$(ctr "$s")" >&2 || true
    die "$s did not become healthy within 180 s"
  done
}
up() { pc up -d --no-deps "$@" >>"$WORK/up.log" 2>&1 || die "compose up $* failed; see $WORK/up.log"; }

log "up: garage-1..3"
up garage-1 garage-2 garage-3
wait_healthy garage-1 garage-2 garage-3
log "up: garage-init (one-shot)"
up garage-init
for _ in $(seq 1 120); do
  [ "$(status '{{.State.Status}}' garage-init)" = exited ] && break
  sleep 1
done
code="$(status '{{.State.ExitCode}}' garage-init)"
pm logs "$(ctr garage-init)" >"$WORK/garage-init.log" 2>&1 || true
[ "$code" = 0 ] || die "garage-init exited with '$code': $(tail -5 "$WORK/garage-init.log")"
log "up: postgres, replicas, nginx"
up postgres
wait_healthy postgres
up replica-1 replica-2
wait_healthy replica-1 replica-2
up nginx
wait_healthy nginx
echo "compose-local: every service up and healthy in $((SECONDS - t0)) s" >&2

# --- 3. checks --------------------------------------------------------------------------------
get() { curl -fsS --max-time 10 "$URL$1"; }
get / >"$WORK/index.html" || die "GET / through nginx failed"
grep -qi voxstream-canvas "$WORK/index.html" || die "GET / through nginx did not return the viewer page"
get /pkg/voxstream_viewer_bg.wasm >"$WORK/viewer.wasm" || die "GET the wasm module through nginx failed"
[ "$(head -c4 "$WORK/viewer.wasm" | od -An -tx1 | tr -d ' \n')" = 0061736d ] ||
  die "the wasm module through nginx has no wasm magic"
log "compose run --rm replica-1 build (the compose file's documented build into the bucket)"
pc run --rm replica-1 build /opt/voxstream/data/koala.obj --out s3://voxstream/scenes --resolution 256 \
  >"$WORK/run-build.log" 2>&1 || die "the documented build failed: $(tail -5 "$WORK/run-build.log")"
wait_listed() { # wait_listed ID: both replicas list it (nginx alternates between them)
  for _ in $(seq 1 60); do
    a="$(get /api/scenes || true)"
    b="$(get /api/scenes || true)"
    if grep -q "\"id\": *\"$1\"" <<<"$a" && grep -q "\"id\": *\"$1\"" <<<"$b"; then return 0; fi
    sleep 1
  done
  die "scene $1 is not listed through nginx: $a"
}
wait_listed koala
get /api/scenes/koala/manifest >"$WORK/manifest.json" || die "GET the manifest failed"
key="$(grep -Eo '"key": *"[0-9]+-[0-9]+-[0-9]+-[0-9]+"' "$WORK/manifest.json" | head -n1 | cut -d'"' -f4 || true)"
[ -n "$key" ] || die "no block key in the manifest"
for i in 1 2 3 4; do
  get "/api/scenes/koala/blocks/$key" >"$WORK/block-$i.vxb" || die "GET block $key failed"
  [ "$(head -c4 "$WORK/block-$i.vxb")" = VXB2 ] || die "block $key does not start with VXB2"
  cmp -s "$WORK/block-1.vxb" "$WORK/block-$i.vxb" || die "the replicas serve different bytes for $key"
done

log "upload through nginx with the token: built once by the replicas"
code="$(curl -sS -o "$WORK/upload.json" -w '%{http_code}' --max-time 60 -H "Authorization: Bearer $TOKEN" \
  --data-binary @"$ROOT/data/koala.obj" "$URL/api/scenes?filename=koala.obj&id=uploaded&resolution=128")"
[ "${code:0:1}" = 2 ] || die "upload answered $code: $(cat "$WORK/upload.json")"
wait_listed uploaded
claims="$( (pm logs "$(ctr replica-1)" 2>&1; pm logs "$(ctr replica-2)" 2>&1) | sed 's/\x1b\[[0-9;]*m//g')"
n="$(grep 'build claimed' <<<"$claims" | grep -c 'scene=uploaded' || true)"
[ "$n" = 1 ] || die "the upload's build was claimed $n times (want exactly once)"

log "kill replica-1: block GETs through nginx keep answering"
pm kill "$(ctr replica-1)" >/dev/null
fails=0
for _ in $(seq 1 40); do get "/api/scenes/koala/blocks/$key" >/dev/null 2>&1 || fails=$((fails + 1)); done
[ "$fails" = 0 ] || die "$fails of 40 block GETs failed with replica-1 killed"
pm start "$(ctr replica-1)" >/dev/null
wait_healthy replica-1

log "kill garage-3: reads and a build keep working (quorum 2 of 3)"
pm kill "$(ctr garage-3)" >/dev/null
pc run --rm replica-2 build /opt/voxstream/data/koala.obj --out s3://voxstream/scenes --name degraded \
  --resolution 128 >"$WORK/run-build-degraded.log" 2>&1 ||
  die "a build with one Garage node down failed: $(tail -5 "$WORK/run-build-degraded.log")"
wait_listed degraded
get "/api/scenes/degraded/manifest" >/dev/null || die "GET the degraded build's manifest failed"
pm start "$(ctr garage-3)" >/dev/null
wait_healthy garage-3

get /api/scenes >"$WORK/scenes.json" || die "GET /api/scenes failed"
echo "compose-local: passed in $((SECONDS - t0)) s: $(head -c 300 "$WORK/scenes.json")" >&2
