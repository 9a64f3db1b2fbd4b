# Sourced by the container scripts: checks podman and the host CLI, sets `base` (the base
# image: $BASE, or the local one scripts/container-base.sh makes) and, on hosts where podman's
# defaults cannot start containers, CONTAINERS_CONF (see docker/containers.conf).
cli=build/release/bin/lsqsurf
command -v podman >/dev/null || { echo "$0: podman is missing (scripts/install-deps.sh --with-containers)" >&2; exit 2; }
[[ -x $cli ]] || { echo "$0: build the CLI first (cmake --preset release && cmake --build --preset release)" >&2; exit 2; }
base=${BASE:-}
if [[ -z $base ]]; then
  scripts/container-base.sh
  base=localhost/debian:bookworm
fi
if [[ -z ${CONTAINERS_CONF:-} ]] && ! podman run --rm "$base" true >/dev/null 2>&1; then
  export CONTAINERS_CONF=$PWD/docker/containers.conf
  echo "$0: podman's defaults cannot start containers here; using $CONTAINERS_CONF"
  podman run --rm "$base" true
fi
# The host's CA bundle as a build secret (docker/Dockerfile: host_ca), for a host that reaches
# npm through a certificate authority only it trusts; no layer of the image keeps it.
host_ca_secret=()
for ca in "${NODE_EXTRA_CA_CERTS:-}" "${SSL_CERT_FILE:-}" /etc/ssl/certs/ca-certificates.crt; do
  if [[ -n $ca && -s $ca ]]; then
    host_ca_secret=(--secret "id=host_ca,src=$ca")
    break
  fi
done
free_port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
