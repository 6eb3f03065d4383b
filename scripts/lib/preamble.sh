# shellcheck shell=bash
# Sourced by the project's scripts after they set SCRIPT_NAME: messages go to stderr prefixed
# with the script's name, so a CI log says which script spoke.

log() { printf '%s: %s\n' "$SCRIPT_NAME" "$*" >&2; }

die() {
  printf '%s: ERROR: %s\n' "$SCRIPT_NAME" "$*" >&2
  exit 1
}

# A loopback TCP port nothing listens on now (the kernel's pick; closed before it is used).
free_port() {
  python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1]); s.close()'
}
