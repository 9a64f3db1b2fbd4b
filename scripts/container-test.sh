#!/usr/bin/env bash
# Builds the container image and checks it end to end on this host, all on loopback:
# runs it with a data volume, waits for its health check, reconstructs the bundled sample
# through the published port with the host's CLI, restarts the container (SIGTERM, then a new
# start on the same volume) and fetches the same result again, byte for byte. Prints the image
# size and the times. Not part of CI (the image build compiles the project inside, minutes).
#   scripts/container-test.sh
# Needs podman and debootstrap (scripts/install-deps.sh --with-containers) and the host CLI
# (build/release/bin/lsqsurf). BASE=debian:bookworm uses a registry's base image instead of the
# local one that scripts/container-base.sh makes.
set -euo pipefail
cd "$(dirname "$0")/.."

source scripts/container-env.sh
image=localhost/lsqsurf:test
name=lsqsurf-test-$$
volume=lsqsurf-test-data-$$

out=$(mktemp -d)
cleanup() {
  podman rm -f "$name" >/dev/null 2>&1 || true
  podman volume rm -f "$volume" >/dev/null 2>&1 || true
  rm -rf "$out"
}
trap cleanup EXIT

start=$(date +%s)
podman build --format docker "${host_ca_secret[@]}" --build-arg "BASE=$base" -f docker/Dockerfile -t "$image" .
built=$(date +%s)
echo "container-test: image built in $((built - start)) s, $(podman image inspect "$image" --format '{{.Size}}') bytes"

port=$(free_port)
server=127.0.0.1:$port
podman volume create "$volume" >/dev/null
run() { podman run -d --name "$name" -p "$server:50051" -v "$volume:/data" "$image" --plaintext >/dev/null; }
wait_healthy() {
  for _ in $(seq 60); do
    if "$cli" --server "$server" health --timeout 2 >/dev/null 2>&1; then return 0; fi
    sleep 1
  done
  echo "container-test: the server did not become healthy; its log:" >&2
  podman logs "$name" >&2
  return 1
}

run
wait_healthy
[[ $(podman exec "$name" id -u) == 10001 ]] || { echo "container-test: the server does not run as its own user" >&2; exit 1; }
podman healthcheck run "$name"
id=$("$cli" --server "$server" submit samples/spot-30k.ply --method pu)
"$cli" --server "$server" watch "$id" >/dev/null
"$cli" --server "$server" fetch "$id" -o "$out/before.drc"
echo "container-test: job $id reconstructed through port $port"

# A graceful stop, then a new container on the same volume: the job and its result are kept.
podman stop --time 30 "$name" >/dev/null
podman rm "$name" >/dev/null
run
wait_healthy
"$cli" --server "$server" status "$id"
"$cli" --server "$server" fetch "$id" -o "$out/after.drc"
cmp "$out/before.drc" "$out/after.drc"
echo "container-test: after a restart the result is fetched again, byte for byte; all checks passed in $(($(date +%s) - start)) s"
