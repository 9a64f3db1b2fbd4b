#!/usr/bin/env bash
# What TLS and tokens cost an upload: two lsqsurfd on loopback, one plaintext without tokens, one
# with TLS (a CA and certificate made here with openssl) and --auth-tokens, and the same uploads
# of a 1M-point cloud to each, cancelled at once so that no job competes with the next upload.
#
#   scripts/tls-bench.sh [POINTS] [UPLOADS] [ROUNDS]
#       defaults: 1000000 points, 5 uploads per server and round, 6 rounds
#
# Prints the median SubmitJob latency per server and round, and the median over the rounds of
# each round's overhead. Needs a release build and openssl; run it on an otherwise idle machine.
set -euo pipefail
cd "$(dirname "$0")/.."

points=${1:-1000000}
uploads=${2:-5}
rounds=${3:-6}
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
run_plain() { "${load[@]}" --server "$plain" >"$1"; }
run_secure() { LSQSURF_TOKEN=$(cat "$work/bench.token") "${load[@]}" --server "$secure" --tls-ca "$work/ca.crt" >"$1"; }
p50() { sed -n 's/^SubmitJob .*p50 \([0-9.]*\) .*/\1/p' "$1"; }
# Rounds alternate which server goes first, and each round compares its own pair of medians, so
# that a drift of the machine's speed over the run does not count as overhead.
for round in $(seq "$rounds"); do
  if ((round % 2)); then
    run_plain "$work/plain.$round"
    run_secure "$work/secure.$round"
  else
    run_secure "$work/secure.$round"
    run_plain "$work/plain.$round"
  fi
  printf 'round %d: plaintext p50 %s ms, TLS + token p50 %s ms\n' "$round" "$(p50 "$work/plain.$round")" \
    "$(p50 "$work/secure.$round")"
done
for round in $(seq "$rounds"); do printf '%s %s\n' "$(p50 "$work/plain.$round")" "$(p50 "$work/secure.$round")"; done |
  python3 -c "
import statistics, sys
pairs = [tuple(map(float, line.split())) for line in sys.stdin]
plain = statistics.median(a for a, _ in pairs)
secure = statistics.median(b for _, b in pairs)
paired = statistics.median(100 * (b - a) / a for a, b in pairs)
print(f'median upload: plaintext {plain:.1f} ms, TLS + token {secure:.1f} ms; median paired overhead {paired:+.1f} %')
"
