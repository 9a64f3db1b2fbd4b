#!/usr/bin/env bash
# Soak test: one lsqsurfd on loopback under a mixed load of concurrent clients (small and large
# clouds, truncated uploads, cancels, watches, fetches, GetJob polls), killed with SIGKILL and
# restarted every few minutes. Afterwards it checks that every accepted job reached a terminal
# state, that every succeeded job's results decode, and that no file or row is orphaned.
#
#   scripts/soak.sh [--minutes 30] [--clients 8] [--kill-every-s 150] [--max-queue 4]
#
# Prints lsqsurf-load's report (per-call latency percentiles, refusals by status code, jobs
# completed), the number of restarts and the checks; exits non-zero if a check fails. Needs a
# release build (cmake --preset release && cmake --build --preset release). Every loop is bounded
# in count and time; all traffic stays on 127.0.0.1.
set -euo pipefail
cd "$(dirname "$0")/.."

minutes=30
clients=8
kill_every=150
max_queue=4  # Fewer than the clients: overload must be answered with RESOURCE_EXHAUSTED.
while (($#)); do
  case "$1" in
    --minutes) minutes=$2; shift 2 ;;
    --clients) clients=$2; shift 2 ;;
    --kill-every-s) kill_every=$2; shift 2 ;;
    --max-queue) max_queue=$2; shift 2 ;;
    *) echo "soak: unknown option $1 (see the header of this script)" >&2; exit 2 ;;
  esac
done

bin=build/release/bin
work=$(mktemp -d /tmp/lsqsurf-soak.XXXXXX)
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
address=127.0.0.1:$port
server_pid=
load_pid=
cleanup() {
  [[ -n $load_pid ]] && kill "$load_pid" 2>/dev/null || true
  [[ -n $server_pid ]] && kill "$server_pid" 2>/dev/null || true
  wait 2>/dev/null || true
  echo "soak: logs and data kept in $work"
}
trap cleanup EXIT

start_server() {
  "$bin/lsqsurfd" --listen "$address" --data-dir "$work/data" --max-queue "$max_queue" --workers 1 \
    >>"$work/server.out" 2>>"$work/server.log" &
  server_pid=$!
  for _ in $(seq 100); do
    "$bin/lsqsurf" --server "$address" health --timeout 1 >/dev/null 2>&1 && return 0
    sleep 0.2
  done
  echo "soak: lsqsurfd did not come up on $address" >&2
  exit 1
}

start_server
echo "soak: lsqsurfd on $address, data in $work/data; $clients clients for $minutes min, SIGKILL every ${kill_every}s"
# Clouds sampled on the shared spot mesh (3k points, every 6th upload 200k); without it, the
# bundled 30k-point sample for every upload.
clouds=(--cloud ../shared/data/meshes/spot.obj --points 3000 --large-points 200000 --large-every 6)
[[ -f ../shared/data/meshes/spot.obj ]] || clouds=(--cloud samples/spot-30k.ply)
"$bin/lsqsurf-load" --server "$address" "${clouds[@]}" --bad-every 7 --cancel-every 5 --jobs 0 \
  --duration-s $((minutes * 60)) --drain-s 900 --submitters "$clients" --pollers 2 --poll-interval-ms 20 \
  --accepted "$work/accepted.txt" >"$work/load.txt" 2>"$work/load.log" &
load_pid=$!

restarts=0
end=$((SECONDS + minutes * 60 + 900))
while kill -0 "$load_pid" 2>/dev/null && ((SECONDS < end)); do
  for _ in $(seq "$kill_every"); do
    kill -0 "$load_pid" 2>/dev/null || break
    sleep 1
  done
  # Only while the load still submits: the drain afterwards runs on a steady server.
  ((SECONDS < minutes * 60)) || continue
  kill -KILL "$server_pid"
  wait "$server_pid" 2>/dev/null || true
  restarts=$((restarts + 1))
  start_server
done
load_status=0
wait "$load_pid" || load_status=$?
load_pid=
cat "$work/load.txt"
echo "soak: $restarts SIGKILL restarts; load exit status $load_status"

# One more restart, then every accepted job must be on record, ended, and its results decode.
kill -KILL "$server_pid"
wait "$server_pid" 2>/dev/null || true
start_server
verify_status=0
"$bin/lsqsurf-load" --server "$address" --verify "$work/accepted.txt" --drain-s 900 || verify_status=$?

# Orphans: a job folder without a job, a job without its folder, a temporary file left behind.
"$bin/lsqsurf" --server "$address" list >"$work/jobs.txt"
listed=$(awk '{print $1}' "$work/jobs.txt" | sort)
folders=$(ls "$work/data/jobs" | sort)
orphan_folders=$(comm -13 <(echo "$listed") <(echo "$folders") | grep -c . || true)
missing_folders=$(comm -23 <(echo "$listed") <(echo "$folders") | grep -c . || true)
temporaries=$(find "$work/data/jobs" -name '*.tmp.*' | wc -l)
echo "soak: $(echo "$listed" | grep -c .) jobs on record; orphaned folders $orphan_folders," \
  "jobs without a folder $missing_folders, temporary files $temporaries"
kill "$server_pid"
wait "$server_pid" 2>/dev/null || true
server_pid=

if ((load_status != 0 || verify_status != 0 || orphan_folders != 0 || missing_folders != 0 || temporaries != 0)); then
  echo "soak: FAILED"
  exit 1
fi
echo "soak: passed"
rm -rf "$work"
trap - EXIT
