#!/bin/sh
# Container entrypoint for voxstream.
#   no arguments: build the default scan into $VOXSTREAM_STORE if it holds no scene yet, then
#                 serve it on $VOXSTREAM_ADDR with the viewer from $VOXSTREAM_WEB. Uploads,
#                 renames and deletes need $VOXSTREAM_TOKEN; without one the server is read-only
#                 (it refuses to open writing to the network without a token). Every other
#                 `voxstream serve` flag has a VOXSTREAM_* variable too (see docker/README.md).
#   arguments:    run the voxstream binary with them (e.g. `build /in/scan.ply --out /store`)
set -eu

BIN=/usr/local/bin/voxstream
STORE="${VOXSTREAM_STORE:-/store}"
ADDR="${VOXSTREAM_ADDR:-0.0.0.0:8080}"
WEB="${VOXSTREAM_WEB:-}" # empty: the viewer embedded in the binary
MESH="${VOXSTREAM_DEFAULT_MESH:-/opt/voxstream/data/koala.obj}"

if [ "$#" -gt 0 ]; then
  exec "$BIN" "$@"
fi

if [ ! -d "$STORE" ] || [ ! -w "$STORE" ]; then
  echo "voxstream-entrypoint: $STORE must be a directory writable by uid $(id -u)" >&2
  exit 1
fi

has_scene=0
for manifest in "$STORE"/*/manifest.json; do
  if [ -f "$manifest" ]; then
    has_scene=1
    break
  fi
done

if [ "$has_scene" -eq 0 ]; then
  echo "voxstream-entrypoint: $STORE has no scene yet; building $MESH (first start only)" >&2
  "$BIN" build "$MESH" --out "$STORE"
fi

READ_ONLY=""
if [ -z "${VOXSTREAM_TOKEN:-}" ]; then
  echo "voxstream-entrypoint: no VOXSTREAM_TOKEN: serving read-only (set it to allow uploads)" >&2
  READ_ONLY="--read-only"
fi

echo "voxstream-entrypoint: serving $STORE on $ADDR" >&2
# shellcheck disable=SC2086 # READ_ONLY is one flag or nothing
WEB_ARGS=""
if [ -n "$WEB" ]; then
  WEB_ARGS="--web $WEB"
fi
# shellcheck disable=SC2086 # READ_ONLY and WEB_ARGS are empty or whole flags
exec "$BIN" serve --store "$STORE" --addr "$ADDR" $WEB_ARGS $READ_ONLY
