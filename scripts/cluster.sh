#!/usr/bin/env bash
# A local voxstream cluster for development, the topology docker/compose.yaml deploys:
#
#   bash scripts/cluster.sh start [DIR]     start it (DIR default: ./cluster), print the URL, return
#   bash scripts/cluster.sh stop [DIR]      stop every process it started
#   bash scripts/cluster.sh build MESH [DIR] [voxstream build options...]
#                                           build a mesh into the cluster's bucket
#   bash scripts/cluster.sh restart replica|garage I [DIR]
#                                           start a killed replica or Garage node again
#   bash scripts/cluster.sh postgres start|stop DIR
#                                           the coordinator alone (prints its URL; password in DIR/pg.env)
#   bash scripts/cluster.sh tools           install Garage, nginx and PostgreSQL (scripts/test.sh does,
#                                           before the tests that start clusters)
#
# What runs, all on loopback ports that were free at start:
#   - three Garage nodes (S3-compatible object store, `scripts/garage.sh` installs it), one zone
#     each, replication factor 3 (reads and writes go on with one node down: quorum 2);
#   - a bucket `voxstream` and a key allowed on it, created with the garage CLI; the key is written
#     to DIR/s3.env (mode 600) as AWS_* lines, which voxstream reads through VOXSTREAM_S3_ENV_FILE;
#   - PostgreSQL (Debian's, installed with apt when missing), the replicas' coordinator: build
#     leases and tus upload state. Its data folder is DIR/postgres (initdb'd on the first start,
#     kept across stop/start), TCP on loopback with a password (scram-sha-256) for the role
#     `voxstream`, written to DIR/pg.env (mode 600) as PGPASSWORD, which voxstream reads through
#     VOXSTREAM_PG_ENV_FILE; as root it runs as the `postgres` user;
#   - two `voxstream serve --store s3://voxstream/scenes --coordinator postgres://…` replicas
#     (stateless: nothing on their disks), each talking to a different Garage node; they take
#     uploads (tus) and build each once between them;
#   - nginx (Debian's nginx-light, installed with apt when missing) in front of the replicas, as a
#     user would deploy them: round robin, and a GET that fails on one replica (connection refused,
#     timeout, 502/503/504) is retried on the other.
#
# DIR/cluster.env then names everything: URL (nginx), REPLICA_URLS, REPLICA_PIDS, GARAGE_PIDS,
# GARAGE_S3 (each node's S3 endpoint), NGINX_PID, COORDINATOR (the replicas' --coordinator URL,
# no password in it) and PG_ENV (the file holding the password), so tests can kill and restart
# parts (`restart replica|garage I`).
#
# Environment: VOXSTREAM_BIN (default: target/release/voxstream, built when missing),
# CLUSTER_PORT (nginx's port, default a free one), CLUSTER_LEASE_SECS (the replicas'
# --lease-secs, default 30; tests shorten it), CLUSTER_GC_INTERVAL_SECS and CLUSTER_GC_GRACE_SECS
# (the replicas' --gc-interval-secs and --gc-grace-secs, default 3600 each; tests shorten the
# grace). `restart replica` reads them again from its own environment.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
CARGO_HOME="${CARGO_HOME:-$HOME/.cargo}"
export PATH="$CARGO_HOME/bin:$PATH:/usr/sbin"

SCRIPT_NAME=cluster
# shellcheck source=scripts/lib/preamble.sh
. "$(dirname "${BASH_SOURCE[0]}")/lib/preamble.sh"

BUCKET="voxstream"
PREFIX="scenes"

wait_for() {
  # wait_for SECONDS WHAT CMD... : retries CMD until it succeeds or SECONDS pass.
  local seconds="$1" what="$2"
  shift 2
  local until=$((SECONDS + seconds))
  until "$@" >/dev/null 2>&1; do
    [ "$SECONDS" -lt "$until" ] || return 1
    sleep 0.2
  done
  log "$what is up"
}

voxstream_bin() {
  if [ -n "${VOXSTREAM_BIN:-}" ]; then
    [ -x "$VOXSTREAM_BIN" ] || die "VOXSTREAM_BIN=$VOXSTREAM_BIN is not an executable"
    printf '%s\n' "$VOXSTREAM_BIN"
    return
  fi
  local bin="${CARGO_TARGET_DIR:-$ROOT/target}/release/voxstream"
  if [ ! -x "$bin" ]; then
    log "cargo build --release -p voxstream"
    (cd "$ROOT" && cargo build --release -p voxstream --bin voxstream >&2) || die "building voxstream failed"
  fi
  printf '%s\n' "$bin"
}

ensure_nginx() {
  command -v nginx >/dev/null 2>&1 && return 0
  log "installing nginx-light with apt"
  local sudo=()
  [ "$(id -u)" -ne 0 ] && sudo=(sudo -n)
  "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends nginx-light >&2 ||
    { "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -q >&2 &&
      "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends nginx-light >&2; } ||
    die "nginx is missing and apt could not install nginx-light"
  command -v nginx >/dev/null 2>&1 || die "nginx-light installed but nginx is not on PATH"
}

pg_bin() {
  # The newest installed PostgreSQL's bin folder (Debian keeps them versioned).
  local dir
  dir="$(find /usr/lib/postgresql -mindepth 2 -maxdepth 2 -name bin -type d 2>/dev/null | sort -V | tail -1)"
  [ -n "$dir" ] && [ -x "$dir/initdb" ] && printf '%s\n' "$dir"
}

ensure_postgres() {
  pg_bin >/dev/null && return 0
  log "installing postgresql with apt"
  local sudo=()
  [ "$(id -u)" -ne 0 ] && sudo=(sudo -n)
  "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends postgresql >&2 ||
    { "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -q >&2 &&
      "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends postgresql >&2; } ||
    die "PostgreSQL is missing and apt could not install postgresql"
  pg_bin >/dev/null || die "postgresql installed but no /usr/lib/postgresql/*/bin/initdb"
}

as_pg() {
  # PostgreSQL refuses to run as root: as root, its tools run as the postgres user.
  if [ "$(id -u)" -eq 0 ]; then runuser -u postgres -- "$@"; else "$@"; fi
}

start_postgres() {
  # Starts the coordinator (initdb on the first start) and creates its role and database once.
  local pgdir="$DIR/postgres" bin
  bin="$(pg_bin)" || die "no PostgreSQL (bash scripts/cluster.sh tools)"
  mkdir -p "$pgdir/run"
  if [ "$(id -u)" -eq 0 ]; then
    chmod 711 "$DIR" # postgres must reach its folder inside; the files here stay unreadable to it
    chown -R postgres: "$pgdir"
  fi
  chmod 700 "$pgdir"
  if [ ! -f "$pgdir/data/PG_VERSION" ]; then
    # Socket connections (inside pgdir, mode 700) are trusted: only its owner reaches them.
    # --no-sync: a development cluster; initdb's fsyncs cost seconds on a busy disk.
    as_pg "$bin/initdb" -D "$pgdir/data" -U postgres --auth-local=trust --auth-host=scram-sha-256 \
      --encoding=UTF8 --locale=C.UTF-8 --no-sync >"$pgdir/initdb.log" 2>&1 ||
      die "initdb failed: $(tail -5 "$pgdir/initdb.log")"
  fi
  local port
  port="$(free_port)"
  as_pg "$bin/pg_ctl" -D "$pgdir/data" -l "$pgdir/postgres.log" -w -t 30 \
    -o "-p $port -c listen_addresses=127.0.0.1 -c unix_socket_directories=$pgdir/run -c unix_socket_permissions=0700" \
    start >/dev/null || die "PostgreSQL did not start: $(tail -5 "$pgdir/postgres.log")"
  log "postgres is up"
  if [ ! -f "$DIR/pg.env" ]; then
    (
      umask 077
      printf 'PGPASSWORD=%s\n' "$(od -An -N24 -tx1 /dev/urandom | tr -d ' \n')" >"$DIR/pg.env"
    )
  fi
  local password
  password="$(sed -n 's/^PGPASSWORD=//p' "$DIR/pg.env")"
  # The password reaches psql on its stdin, never as an argument (ps shows those).
  printf '%s\n' \
    "SELECT 'CREATE ROLE voxstream LOGIN' WHERE NOT EXISTS (SELECT 1 FROM pg_roles WHERE rolname = 'voxstream')\\gexec" \
    "ALTER ROLE voxstream PASSWORD '$password';" \
    "SELECT 'CREATE DATABASE voxstream OWNER voxstream' WHERE NOT EXISTS (SELECT 1 FROM pg_database WHERE datname = 'voxstream')\\gexec" |
    as_pg "$bin/psql" -h "$pgdir/run" -p "$port" -U postgres -d postgres -v ON_ERROR_STOP=1 -q >/dev/null ||
    die "creating the coordinator's role and database failed: $(tail -5 "$pgdir/postgres.log")"
  COORDINATOR="postgres://voxstream@127.0.0.1:$port/voxstream"
}

stop_postgres() {
  local pgdir="$DIR/postgres" bin
  [ -f "$pgdir/data/postmaster.pid" ] || return 0
  bin="$(pg_bin)" || return 0
  as_pg "$bin/pg_ctl" -D "$pgdir/data" -m fast -w -t 30 stop >/dev/null 2>&1 || true
}

start_garage_node() {
  # start_garage_node I : runs node I from its config, appends its pid.
  local i="$1"
  setsid "$GARAGE" -c "$DIR/garage-$i/garage.toml" server >"$DIR/garage-$i/garage.log" 2>&1 </dev/null &
  echo $! >"$DIR/garage-$i/pid"
}

start_replica() {
  # start_replica I : runs replica I against Garage node I's S3 endpoint.
  local i="$1"
  setsid env VOXSTREAM_S3_ENV_FILE="$DIR/s3-$i.env" VOXSTREAM_PG_ENV_FILE="$DIR/pg.env" \
    RUST_LOG="${RUST_LOG:-warn,voxstream=info}" \
    "$VOXSTREAM" serve --store "s3://$BUCKET/$PREFIX" --addr "127.0.0.1:$(cat "$DIR/replica-$i/port")" \
    --relist-secs 2 --coordinator "$COORDINATOR" --lease-secs "${CLUSTER_LEASE_SECS:-30}" \
    --gc-interval-secs "${CLUSTER_GC_INTERVAL_SECS:-3600}" --gc-grace-secs "${CLUSTER_GC_GRACE_SECS:-3600}" \
    >"$DIR/replica-$i/out.log" 2>"$DIR/replica-$i/err.log" </dev/null &
  echo $! >"$DIR/replica-$i/pid"
}

cmd_start() {
  [ -e "$DIR/cluster.env" ] && die "$DIR holds a cluster already (bash scripts/cluster.sh stop $DIR first)"
  mkdir -p "$DIR"
  DIR="$(cd "$DIR" && pwd)"
  GARAGE="$(bash "$ROOT/scripts/garage.sh")" || die "scripts/garage.sh failed"
  VOXSTREAM="$(voxstream_bin)"
  ensure_nginx
  ensure_postgres
  local secret
  secret="$(od -An -N32 -tx1 /dev/urandom | tr -d ' \n')"

  # --- three Garage nodes, replication factor 3 --------------------------------------------------
  local i rpc s3 admin
  for i in 1 2 3; do
    rpc="$(free_port)" s3="$(free_port)" admin="$(free_port)"
    mkdir -p "$DIR/garage-$i"
    cat >"$DIR/garage-$i/garage.toml" <<EOF
metadata_dir = "$DIR/garage-$i/meta"
data_dir = "$DIR/garage-$i/data"
db_engine = "sqlite"
replication_factor = 3
rpc_bind_addr = "127.0.0.1:$rpc"
rpc_public_addr = "127.0.0.1:$rpc"
rpc_secret = "$secret"

[s3_api]
s3_region = "garage"
api_bind_addr = "127.0.0.1:$s3"
root_domain = ".s3.garage.localhost"

[admin]
api_bind_addr = "127.0.0.1:$admin"
EOF
    chmod 600 "$DIR/garage-$i/garage.toml"
    echo "$s3" >"$DIR/garage-$i/s3port"
    start_garage_node "$i"
  done
  local g1=("$GARAGE" -c "$DIR/garage-1/garage.toml")
  local ids=()
  for i in 1 2 3; do
    wait_for 30 "garage node $i" "$GARAGE" -c "$DIR/garage-$i/garage.toml" node id -q ||
      die "garage node $i did not start: $(tail -5 "$DIR/garage-$i/garage.log")"
    ids+=("$("$GARAGE" -c "$DIR/garage-$i/garage.toml" node id -q)")
  done
  for i in 1 2; do
    "${g1[@]}" node connect "${ids[$i]}" >&2 || die "garage node 1 cannot connect to node $((i + 1))"
  done
  for i in 0 1 2; do
    "${g1[@]}" layout assign -z "dc$((i + 1))" -c 1G "${ids[$i]%@*}" >&2
  done
  "${g1[@]}" layout apply --version 1 >&2 || die "garage layout apply failed"
  wait_for 30 "the bucket" "${g1[@]}" bucket create "$BUCKET" || die "garage bucket create failed"
  local key
  key="$("${g1[@]}" key create voxstream-cluster)" || die "garage key create failed"
  local key_id key_secret
  key_id="$(printf '%s\n' "$key" | sed -n 's/^Key ID: *//p')"
  key_secret="$(printf '%s\n' "$key" | sed -n 's/^Secret key: *//p')"
  if [ -z "$key_id" ] || [ -z "$key_secret" ]; then die "could not read the key from garage key create"; fi
  "${g1[@]}" bucket allow --read --write --owner "$BUCKET" --key "$key_id" >&2
  for i in 1 2 3; do
    (
      umask 077
      printf 'AWS_ENDPOINT_URL=http://127.0.0.1:%s\nAWS_ALLOW_HTTP=true\nAWS_REGION=garage\nAWS_ACCESS_KEY_ID=%s\nAWS_SECRET_ACCESS_KEY=%s\n' \
        "$(cat "$DIR/garage-$i/s3port")" "$key_id" "$key_secret" >"$DIR/s3-$i.env"
    )
  done
  cp "$DIR/s3-1.env" "$DIR/s3.env"

  # --- the coordinator ------------------------------------------------------------------------
  start_postgres

  # --- two stateless replicas, each on its own Garage node --------------------------------------
  for i in 1 2; do
    mkdir -p "$DIR/replica-$i"
    free_port >"$DIR/replica-$i/port"
    start_replica "$i"
  done
  for i in 1 2; do
    wait_for 30 "replica $i" curl -fsS "http://127.0.0.1:$(cat "$DIR/replica-$i/port")/healthz" ||
      die "replica $i did not start: $(tail -5 "$DIR/replica-$i/err.log")"
  done

  # --- nginx in front --------------------------------------------------------------------------
  local port="${CLUSTER_PORT:-$(free_port)}"
  mkdir -p "$DIR/nginx/tmp"
  cat >"$DIR/nginx/nginx.conf" <<EOF
worker_processes 1;
pid $DIR/nginx/nginx.pid;
error_log $DIR/nginx/error.log warn;
events { worker_connections 1024; }
http {
  access_log $DIR/nginx/access.log;
  client_body_temp_path $DIR/nginx/tmp/body;
  proxy_temp_path $DIR/nginx/tmp/proxy;
  fastcgi_temp_path $DIR/nginx/tmp/fastcgi;
  uwsgi_temp_path $DIR/nginx/tmp/uwsgi;
  scgi_temp_path $DIR/nginx/tmp/scgi;
  upstream voxstream {
    server 127.0.0.1:$(cat "$DIR/replica-1/port") max_fails=1 fail_timeout=2s;
    server 127.0.0.1:$(cat "$DIR/replica-2/port") max_fails=1 fail_timeout=2s;
    keepalive 16;
  }
  server {
    listen 127.0.0.1:$port;
    client_max_body_size 0;
    location / {
      proxy_pass http://voxstream;
      proxy_http_version 1.1;
      proxy_set_header Connection "";
      proxy_set_header Host \$host;
      # A replica that dies mid-request: idempotent requests go to the other one.
      proxy_next_upstream error timeout http_502 http_503 http_504;
      proxy_next_upstream_tries 2;
      proxy_connect_timeout 2s;
      # Build progress is server-sent events: pass them on as they come; uploads stream through.
      proxy_buffering off;
      proxy_request_buffering off;
      proxy_read_timeout 1h;
    }
  }
}
EOF
  nginx -p "$DIR/nginx" -c "$DIR/nginx/nginx.conf" -e "$DIR/nginx/error.log" || die "nginx did not start"
  wait_for 10 "nginx" curl -fsS "http://127.0.0.1:$port/healthz" || die "nginx does not answer on $port"

  {
    echo "URL=http://127.0.0.1:$port"
    echo "REPLICA_URLS=\"http://127.0.0.1:$(cat "$DIR/replica-1/port") http://127.0.0.1:$(cat "$DIR/replica-2/port")\""
    echo "REPLICA_PIDS=\"$(cat "$DIR/replica-1/pid") $(cat "$DIR/replica-2/pid")\""
    echo "GARAGE_PIDS=\"$(cat "$DIR/garage-1/pid") $(cat "$DIR/garage-2/pid") $(cat "$DIR/garage-3/pid")\""
    echo "GARAGE_S3=\"http://127.0.0.1:$(cat "$DIR/garage-1/s3port") http://127.0.0.1:$(cat "$DIR/garage-2/s3port") http://127.0.0.1:$(cat "$DIR/garage-3/s3port")\""
    echo "NGINX_PID=$(cat "$DIR/nginx/nginx.pid")"
    echo "STORE_URL=s3://$BUCKET/$PREFIX"
    echo "S3_ENV=$DIR/s3.env"
    echo "VOXSTREAM=$VOXSTREAM"
    echo "GARAGE=$GARAGE"
    echo "COORDINATOR=$COORDINATOR"
    echo "PG_ENV=$DIR/pg.env"
    echo "LEASE_SECS=${CLUSTER_LEASE_SECS:-30}"
  } >"$DIR/cluster.env"
  log "up: http://127.0.0.1:$port/ (nginx → 2 replicas → 3 Garage nodes); state in $DIR/cluster.env"
  log "build a scan into it: bash scripts/cluster.sh build <mesh> $DIR"
  printf 'http://127.0.0.1:%s\n' "$port"
}

cmd_restart() {
  # restart replica|garage I : starts a stopped part again with its old settings.
  local what="$1" i="$2"
  # shellcheck disable=SC1091
  . "$DIR/cluster.env"
  GARAGE="${GARAGE:?}" VOXSTREAM="${VOXSTREAM:?}" COORDINATOR="${COORDINATOR:?}"
  CLUSTER_LEASE_SECS="${LEASE_SECS:-30}"
  case "$what" in
    replica) start_replica "$i" ;;
    garage) start_garage_node "$i" ;;
    *) die "restart replica|garage <1..3>" ;;
  esac
  cat "$DIR/$what-$i/pid"
}

cmd_stop() {
  [ -d "$DIR" ] || die "$DIR does not exist"
  if [ -f "$DIR/nginx/nginx.pid" ]; then
    nginx -p "$DIR/nginx" -c "$DIR/nginx/nginx.conf" -e "$DIR/nginx/error.log" -s quit 2>/dev/null || true
  fi
  local f
  for f in "$DIR"/replica-*/pid "$DIR"/garage-*/pid; do
    if [ -f "$f" ]; then kill "$(cat "$f")" 2>/dev/null || true; fi
  done
  stop_postgres
  rm -f "$DIR/cluster.env"
  log "stopped the cluster in $DIR"
}

cmd_build() {
  local mesh="$1"
  shift
  [ -f "$DIR/cluster.env" ] || die "no cluster in $DIR (bash scripts/cluster.sh start $DIR)"
  # shellcheck disable=SC1091
  . "$DIR/cluster.env"
  VOXSTREAM_S3_ENV_FILE="$DIR/s3.env" "$VOXSTREAM" build "$mesh" --out "s3://$BUCKET/$PREFIX" "$@"
}

action="${1:-}"
shift || true
case "$action" in
  start)
    DIR="${1:-$ROOT/cluster}"
    cmd_start
    ;;
  stop)
    DIR="${1:-$ROOT/cluster}"
    cmd_stop
    ;;
  restart)
    [ $# -ge 2 ] || die "usage: bash scripts/cluster.sh restart replica|garage I [DIR]"
    DIR="${3:-$ROOT/cluster}"
    cmd_restart "$1" "$2"
    ;;
  build)
    [ $# -ge 1 ] || die "usage: bash scripts/cluster.sh build MESH [DIR] [voxstream build options]"
    mesh="$1"
    shift
    DIR="$ROOT/cluster"
    if [ $# -gt 0 ] && [ "${1#-}" = "$1" ]; then
      DIR="$1"
      shift
    fi
    cmd_build "$mesh" "$@"
    ;;
  postgres)
    # postgres start|stop DIR: the coordinator alone (server/tests/coordinator.rs); start prints
    # its URL (the password is in DIR/pg.env).
    [ $# -eq 2 ] || die "usage: bash scripts/cluster.sh postgres start|stop DIR"
    DIR="$2"
    case "$1" in
      start)
        ensure_postgres
        mkdir -p "$DIR"
        DIR="$(cd "$DIR" && pwd)"
        start_postgres
        printf '%s\n' "$COORDINATOR"
        ;;
      stop) stop_postgres ;;
      *) die "usage: bash scripts/cluster.sh postgres start|stop DIR" ;;
    esac
    ;;
  tools)
    bash "$ROOT/scripts/garage.sh" >/dev/null || die "scripts/garage.sh failed"
    ensure_nginx
    ensure_postgres
    log "garage, nginx and postgresql are installed"
    ;;
  *) die "usage: bash scripts/cluster.sh start|stop|restart|build|tools … (see the top of this script)" ;;
esac
