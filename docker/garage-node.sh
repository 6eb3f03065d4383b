#!/bin/sh
# One Garage node of docker/compose.yaml (the topology of scripts/cluster.sh: replication factor 3,
# one zone a node). Writes its config from the environment, then runs the server.
#   GARAGE_NODE_HOST   this node's name on the compose network (rpc_public_addr)
#   GARAGE_RPC_SECRET  64 hex digits, the same on every node (read by garage from the environment)
set -eu
: "${GARAGE_NODE_HOST:?set GARAGE_NODE_HOST}"
: "${GARAGE_RPC_SECRET:?set GARAGE_RPC_SECRET (openssl rand -hex 32)}"
CONFIG=/tmp/garage.toml
cat >"$CONFIG" <<TOML
metadata_dir = "/var/lib/garage/meta"
data_dir = "/var/lib/garage/data"
db_engine = "sqlite"
replication_factor = 3
rpc_bind_addr = "[::]:3901"
rpc_public_addr = "${GARAGE_NODE_HOST}:3901"

[s3_api]
s3_region = "garage"
api_bind_addr = "[::]:3900"
root_domain = ".s3.garage.localhost"
TOML
if [ "$#" -gt 0 ]; then
  exec garage -c "$CONFIG" "$@"
fi
exec garage -c "$CONFIG" server
