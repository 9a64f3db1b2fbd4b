#!/usr/bin/env bash
# Brings up deploy/compose.yaml with podman-compose: PostgreSQL, three lsqsurfd replicas and
# nginx, on images built here from Debian's packages (no registry needed). Reconstructs the
# bundled sample through nginx's published port with the host's CLI, kills the replica that runs
# a second job and checks that another one finishes it, fetches both results through nginx,
# then takes the stack down (volumes included). Not part of CI (the image builds take minutes).
#   scripts/compose-test.sh
# Needs scripts/install-deps.sh --with-containers (podman, podman-compose, the CNI dnsname
# plugin for service names) and a release build of the CLI.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/container-env.sh
command -v podman-compose >/dev/null || { echo "compose-test: podman-compose is missing" >&2; exit 2; }

start=$(date +%s)
podman build --format docker "${host_ca_secret[@]}" --build-arg "BASE=$base" -f docker/Dockerfile -t localhost/lsqsurf:latest .
podman build --build-arg "BASE=$base" -f docker/postgres/Dockerfile -t localhost/lsqsurf-postgres:latest .
podman build --build-arg "BASE=$base" -f docker/nginx/Dockerfile -t localhost/lsqsurf-nginx:latest .
echo "compose-test: images built in $(($(date +%s) - start)) s"

export LSQSURF_IMAGE=localhost/lsqsurf:latest
export LSQSURF_POSTGRES_IMAGE=localhost/lsqsurf-postgres:latest
export LSQSURF_NGINX_IMAGE=localhost/lsqsurf-nginx:latest
LSQSURF_DB_PASSWORD=$(python3 -c 'import secrets; print(secrets.token_hex(16))')
LSQSURF_PORT=$(free_port)
export LSQSURF_DB_PASSWORD LSQSURF_PORT
server=127.0.0.1:$LSQSURF_PORT
compose=(podman-compose -p lsqsurf-test -f deploy/compose.yaml)
out=$(mktemp -d)
cleanup() {
  "${compose[@]}" down -v >/dev/null 2>&1 || true
  rm -rf "$out"
}
trap cleanup EXIT

"${compose[@]}" up -d
for _ in $(seq 90); do "$cli" --server "$server" health --timeout 2 >/dev/null 2>&1 && break; sleep 1; done
"$cli" --server "$server" health --timeout 5

first=$("$cli" -q --server "$server" submit samples/spot-30k.ply --method pu)
"$cli" --server "$server" watch "$first" >/dev/null
"$cli" --server "$server" fetch "$first" -o "$out/first.drc"
echo "compose-test: job $first reconstructed through nginx; ran on $("$cli" --server "$server" status "$first" | sed -n 's/^runner *//p')"

# A second job, long enough to be met running (PU on 400k points of a sphere); the replica
# that runs it is killed, and another one finishes it.
python3 - "$out/sphere.ply" <<'PY'
import math, sys
n = 400000
with open(sys.argv[1], "w") as f:
    f.write(f"ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
            "property float nx\nproperty float ny\nproperty float nz\nend_header\n")
    for i in range(n):
        z = 1 - 2 * (i + 0.5) / n
        r = math.sqrt(1 - z * z)
        a = i * math.pi * (3 - math.sqrt(5))
        x, y = r * math.cos(a), r * math.sin(a)
        f.write(f"{x:.6f} {y:.6f} {z:.6f} {x:.6f} {y:.6f} {z:.6f}\n")
PY
second=$("$cli" -q --server "$server" submit "$out/sphere.ply" --method pu)
runner=""
for _ in $(seq 100); do
  runner=$("$cli" --server "$server" status "$second" | sed -n 's/^runner *//p')
  [[ -n $runner ]] && break
  sleep 0.1
done
victim=${runner%%/*}
podman kill "$(podman ps --filter "label=io.podman.compose.project=lsqsurf-test" --format '{{.Names}}' | grep -- "$victim" | head -1)" >/dev/null
killed=$(date +%s)
"$cli" --server "$server" watch "$second" >/dev/null
"$cli" --server "$server" fetch "$second" -o "$out/second.drc"
echo "compose-test: $victim killed while it ran job $second; it finished on" \
  "$("$cli" --server "$server" status "$second" | sed -n 's/^runner *//p') $(($(date +%s) - killed)) s later"
echo "compose-test: all checks passed in $(($(date +%s) - start)) s"
