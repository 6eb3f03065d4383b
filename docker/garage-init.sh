#!/bin/sh
# The one-shot service of docker/compose.yaml that makes the Garage cluster usable, as
# scripts/cluster.sh does: connects the three nodes, gives each a role in its own zone (replication
# factor 3), creates the bucket `voxstream` and imports the key from GARAGE_KEY_ID /
# GARAGE_SECRET_KEY with read and write on it. Idempotent: a second run finds the bucket and key.
# It reads each node's key from that node's metadata volume, mounted read-only at /meta/<i>.
set -eu
: "${GARAGE_RPC_SECRET:?}" "${GARAGE_KEY_ID:?}" "${GARAGE_SECRET_KEY:?}"
BUCKET="${GARAGE_BUCKET:-voxstream}"

config() {
  # config I: a CLI config that reaches node I with its own node key (Garage 2 refuses a config
  # without [s3_api], even for the CLI).
  cat >"/tmp/garage-$1.toml" <<TOML
metadata_dir = "/meta/$1"
data_dir = "/tmp/unused-data"
db_engine = "sqlite"
replication_factor = 3
rpc_bind_addr = "[::]:3901"
rpc_public_addr = "garage-$1:3901"

[s3_api]
s3_region = "garage"
api_bind_addr = "[::]:3900"
TOML
}

ids=""
for i in 1 2 3; do
  config "$i"
  tries=0
  until id="$(garage -c "/tmp/garage-$i.toml" node id -q 2>/dev/null)"; do
    tries=$((tries + 1))
    [ "$tries" -lt 150 ] || { echo "garage-init: node $i does not answer" >&2; exit 1; }
    sleep 0.2
  done
  ids="$ids $id"
done
g() { garage -c /tmp/garage-1.toml "$@"; }
# shellcheck disable=SC2086 # the ids are words without spaces
set -- $ids
g node connect "$2" >/dev/null
g node connect "$3" >/dev/null
if ! g bucket info "$BUCKET" >/dev/null 2>&1; then
  zone=1
  for id in "$@"; do
    g layout assign -z "dc$zone" -c 1G "${id%@*}"
    zone=$((zone + 1))
  done
  g layout apply --version 1
  tries=0
  until g bucket create "$BUCKET" >/dev/null 2>&1; do
    tries=$((tries + 1))
    [ "$tries" -lt 150 ] || { echo "garage-init: cannot create bucket $BUCKET" >&2; exit 1; }
    sleep 0.2
  done
fi
if ! g key info "$GARAGE_KEY_ID" >/dev/null 2>&1; then
  g key import --yes -n voxstream "$GARAGE_KEY_ID" "$GARAGE_SECRET_KEY" >/dev/null
fi
g bucket allow --read --write --owner "$BUCKET" --key "$GARAGE_KEY_ID" >/dev/null
echo "garage-init: bucket $BUCKET and key $GARAGE_KEY_ID ready"
