#!/usr/bin/env bash
# What TLS and tokens cost an upload: two lsqsurfd on loopback, one plaintext without tokens, one
# with TLS (a CA and certificate made here with openssl) and --auth-tokens, and the same uploads
# of a 1M-point cloud to each, cancelled at once so that no job competes with the next upload.
#
#   scripts/tls-bench.sh [POINTS] [UPLOADS]    defaults: 1000000 points, 7 uploads per server
#
# Prints lsqsurf-load's SubmitJob latencies per server and the overhead of the median. Needs a
# release build and openssl.
set -euo pipefail
cd "$(dirname "$0")/.."

points=${1:-1000000}
uploads=${2:-7}
bin=build/release/bin
work=$(mktemp -d /tmp/lsqsurf-tls-bench.XXXXXX)
pids=()
cleanup() {
  for pid in "${pids[@]}"; do kill "$pid" 2>/dev/null || true; done
  wait 2>/dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT

openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 2 -subj /CN=bench-ca \
  -keyout "$work/ca.key" -out "$work/ca.crt" 2>/dev/null
openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj /CN=127.0.0.1 \
  -keyout "$work/server.key" -out "$work/server.csr" 2>/dev/null
printf 'subjectAltName=IP:127.0.0.1\n' >"$work/san.ext"
openssl x509 -req -in "$work/server.csr" -CA "$work/ca.crt" -CAkey "$work/ca.key" -CAcreateserial -days 2 \
  -extfile "$work/san.ext" -out "$work/server.crt" 2>/dev/null
"$bin/lsqsurfd" tokens add "$work/tokens" bench >"$work/bench.token" 2>/dev/null

start() {  # DATA-DIR FLAGS... ; prints the address
  local out=$work/$1.out
  "$bin/lsqsurfd" --listen 127.0.0.1:0 --data-dir "$work/$1" "${@:2}" >"$out" 2>"$work/$1.log" &
  pids+=($!)
  for _ in $(seq 100); do grep -q "listening on" "$out" 2>/dev/null && break; sleep 0.1; done
  sed -n 's/^listening on //p' "$out"
}
plain=$(start plain)
secure=$(start secure --tls-cert "$work/server.crt" --tls-key "$work/server.key" --auth-tokens "$work/tokens")

load=("$bin/lsqsurf-load" --cloud ../shared/data/meshes/stanford-bunny.obj --points "$points" --method iamls
  --jobs "$uploads" --submitters 1 --pollers 0 --submit-only --cancel-every 1)
echo "== plaintext, no token ($plain)"
"${load[@]}" --server "$plain" | tee "$work/plain.txt" | grep -E "SubmitJob|job "
echo "== TLS and a token ($secure)"
LSQSURF_TOKEN=$(cat "$work/bench.token") "${load[@]}" --server "$secure" --tls-ca "$work/ca.crt" |
  tee "$work/secure.txt" | grep -E "SubmitJob|job "
p50() { sed -n 's/^SubmitJob .*p50 \([0-9.]*\) .*/\1/p' "$1"; }
python3 -c "import sys; a, b = float(sys.argv[1]), float(sys.argv[2]); print(f'median upload: plaintext {a:.1f} ms, TLS + token {b:.1f} ms, overhead {100 * (b - a) / a:+.1f} %')" \
  "$(p50 "$work/plain.txt")" "$(p50 "$work/secure.txt")"
