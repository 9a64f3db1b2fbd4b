#!/usr/bin/env bash
# Replicas on separate machines, simulated: PostgreSQL in one network namespace and three lsqsurfd
# replicas in three others, each joined to the database's namespace by a veth link of its own
# (no loopback, no bridge between replicas), each with its data directory and temporary files on
# a tmpfs of its own mount namespace, so that nothing but the database is shared: jobs, uploads,
# tile plans, points and parts all go through PostgreSQL. The client runs in the database's
# namespace and reaches each replica over its link.
#
#   scripts/netns-replicas.sh [--points N] [--bin DIR] [--keep]
#
# Three runs of one tiled PU job (a cloud sampled from a torus), each checked
# against the mesh a lone server makes of it (same vertex and face counts, Hausdorff distance at
# most 1e-6 of the diagonal, closed, one component):
#   1. a helper is killed (SIGKILL) once both helpers have made tiles: the job's `replicas`
#      statistic is 3 and the killed helper's tile is made again by another;
#   2. the job's coordinator is killed once a third of the tiles are made: another replica
#      takes the job over and reuses the tiles already made (`reused_tiles` > 0);
#   3. one replica is restarted as a server of another build (its tiles are of another format)
#      while the job runs: it claims none of the job's tiles (`replicas` is 2).
#
# Needs root (network and mount namespaces), a release build, and PostgreSQL
# (scripts/install-deps.sh). Exits 77 (skipped) where namespaces cannot be made; `tests/` runs it
# as the ctest Replicas.OnSeparateMachinesSimulated (labels e2e, slow). --bin names the folder of
# lsqsurfd and lsqsurf (default: the release build's); --keep leaves the logs in the printed folder.
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD

points=20000
bin=$repo/build/release/bin
keep=0
while (($#)); do
  case "$1" in
    --points) points=$2; shift 2 ;;
    --bin) bin=$(realpath "$2"); shift 2 ;;
    --keep) keep=1; shift ;;
    *) echo "netns-replicas: unknown option $1 (see the header of this script)" >&2; exit 2 ;;
  esac
done

skip() { echo "netns-replicas: skipped: $*" >&2; exit 77; }
[[ $(id -u) -eq 0 ]] || skip "network namespaces need root"
[[ -x $bin/lsqsurfd && -x $bin/lsqsurf ]] || { echo "netns-replicas: build the release preset first" >&2; exit 1; }
pg_bin=$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | tail -1)
[[ -n $pg_bin ]] || skip "PostgreSQL is not installed (scripts/install-deps.sh)"
command -v ip >/dev/null && command -v unshare >/dev/null || skip "ip (iproute2) and unshare are needed"

tag=$$
db=lsq$tag-db
ip netns add "$db" 2>/dev/null || skip "this machine refuses to make network namespaces"
unshare --mount true 2>/dev/null || { ip netns del "$db"; skip "this machine refuses to make mount namespaces"; }

work=$(mktemp -d /tmp/lsqsurf-netns.XXXXXX)
chmod 755 "$work"  # The postgres user must reach its folder inside.
declare -A pids=()
cleanup() {
  for pid in "${pids[@]}"; do kill -9 "$pid" 2>/dev/null || true; done
  wait 2>/dev/null || true
  if [[ -f $work/pg/data/postmaster.pid ]]; then
    ip netns exec "$db" runuser -u postgres -- "$pg_bin/pg_ctl" -D "$work/pg/data" -m immediate stop >/dev/null 2>&1 || true
  fi
  for i in 0 1 2; do ip netns del "lsq$tag-r$i" 2>/dev/null || true; done
  ip netns del "$db" 2>/dev/null || true
  if ((keep)); then echo "netns-replicas: logs kept in $work"; else rm -rf "$work"; fi
}
trap cleanup EXIT
fail() {
  echo "netns-replicas: FAILED: $*" >&2
  for log in "$work"/*.log "$work/pg/server.log"; do echo "--- tail of $log" >&2; tail -n 15 "$log" >&2; done
  exit 1
}

in_db() { ip netns exec "$db" "$@"; }
client() { in_db "$bin/lsqsurf" --plaintext -q --server "$1" "${@:2}"; }
replica_address() { echo "10.213.$1.2:50051"; }

# The links: replica i is 10.213.i.2, the database's end of its link 10.213.i.1.
ip -n "$db" link set lo up
for i in 0 1 2; do
  ns=lsq$tag-r$i
  ip netns add "$ns"
  ip link add "lq$tag-d$i" netns "$db" type veth peer name "lq$tag-r$i" netns "$ns"
  ip -n "$db" addr add "10.213.$i.1/24" dev "lq$tag-d$i"
  ip -n "$db" link set "lq$tag-d$i" up
  ip -n "$ns" addr add "10.213.$i.2/24" dev "lq$tag-r$i"
  ip -n "$ns" link set "lq$tag-r$i" up
  ip -n "$ns" link set lo up
done

# PostgreSQL, listening on the database's end of each link only.
mkdir -p "$work/pg"
chown postgres "$work/pg"
runuser -u postgres -- "$pg_bin/initdb" -D "$work/pg/data" -A trust -U lsqsurf -E UTF8 --locale=C >/dev/null
echo "host all all 10.213.0.0/16 trust" >>"$work/pg/data/pg_hba.conf"
in_db runuser -u postgres -- "$pg_bin/pg_ctl" -D "$work/pg/data" -l "$work/pg/server.log" -w \
  -o "-p 5432 -k $work/pg -c listen_addresses=10.213.0.1,10.213.1.1,10.213.2.1 -c max_connections=100" \
  start >/dev/null

# Replica i in its namespaces: its data and temporary files on a tmpfs nobody else sees.
start_replica() {
  local i=$1
  shift
  local dir=$work/r$i
  mkdir -p "$dir"
  : >"$work/r$i.out"
  ip netns exec "lsq$tag-r$i" unshare --mount --propagation private bash -c '
      mount -t tmpfs -o size=4g tmpfs "$0" && mkdir -p "$0/data" "$0/tmp" &&
      TMPDIR="$0/tmp" exec "$@"' "$dir" \
    "$bin/lsqsurfd" --listen "$(replica_address "$i")" --plaintext --data-dir "$dir/data" --name "r$i" \
    --workers 1 --lease-seconds 3 --store "postgresql://lsqsurf@10.213.$i.1:5432/postgres" "$@" \
    >>"$work/r$i.out" 2>>"$work/r$i.log" &
  pids[$i]=$!
  for _ in $(seq 200); do grep -q "listening on" "$work/r$i.out" && return; sleep 0.1; done
  fail "replica r$i did not start"
}

stat_of() { sed -n "s/^stat *$2=//p" <<<"$1"; }
field_of() { sed -n "s/^$2 *//p" <<<"$1" | head -1; }
wait_done() {
  local address=$1 id=$2 status
  client "$address" watch "$id" >/dev/null 2>&1 || true
  status=$(client "$address" status "$id")
  [[ $(field_of "$status" state) == succeeded ]] || fail "job $id: $(field_of "$status" state): $(field_of "$status" error)"
  echo "$status"
}
# Tiles of job $1 made so far, over every replica's log.
tiles_made() { cat "$work"/r?.log | grep -c "\[job $1\] tile [0-9]* made here" || true; }
made_by() { grep -c "\[job $2\] tile [0-9]* made here" "$work/r$1.log" || true; }
coordinator_of() {
  local runner
  runner=$(field_of "$(client "$1" status "$2")" runner)
  [[ $runner =~ ^r([0-9])/ ]] && echo "${BASH_REMATCH[1]}"
}
wait_for() {  # wait_for SECONDS DESCRIPTION COMMAND...
  local seconds=$1 what=$2
  shift 2
  for _ in $(seq $((seconds * 10))); do "$@" && return; sleep 0.1; done
  fail "waited ${seconds} s for $what"
}

# The cloud: sampled from a torus (closed, genus one) written here, so that nothing outside the
# repository is needed.
python3 - "$work/torus.obj" <<'PY'
import math, sys
rings, sides, big, small = 96, 48, 1.0, 0.35
with open(sys.argv[1], "w") as out:
    for i in range(rings):
        u = 2 * math.pi * i / rings
        for j in range(sides):
            v = 2 * math.pi * j / sides
            r = big + small * math.cos(v)
            out.write(f"v {r * math.cos(u):.9f} {r * math.sin(u):.9f} {small * math.sin(v):.9f}\n")
    for i in range(rings):
        for j in range(sides):
            a, b = i * sides + j, ((i + 1) % rings) * sides + j
            c, d = ((i + 1) % rings) * sides + (j + 1) % sides, i * sides + (j + 1) % sides
            out.write(f"f {a + 1} {b + 1} {c + 1}\nf {a + 1} {c + 1} {d + 1}\n")
PY
"$bin/lsqsurf" sample "$work/torus.obj" -o "$work/cloud.ply" --points "$points" >/dev/null
job=("$work/cloud.ply" --method pu --param tile_points=2000 --param support_cap=16 --part-points 10000)

# The reference: a lone server with a store of its own, in the database's namespace.
mkdir -p "$work/alone"
in_db "$bin/lsqsurfd" --listen 127.0.0.1:50051 --data-dir "$work/alone" --workers 1 >"$work/alone.out" 2>"$work/alone.log" &
pids[alone]=$!
wait_for 20 "the lone server" grep -q "listening on" "$work/alone.out"
alone_id=$(client 127.0.0.1:50051 submit "${job[@]}")
alone=$(wait_done 127.0.0.1:50051 "$alone_id")
client 127.0.0.1:50051 fetch "$alone_id" -o "$work/alone.ply"
kill "${pids[alone]}"
unset 'pids[alone]'
tiles=$(stat_of "$alone" tiles)
((tiles >= 12)) || fail "the job has only $tiles tiles: too few to share"
echo "netns-replicas: alone: $tiles tiles, $(stat_of "$alone" vertices) vertices, $(stat_of "$alone" wall_seconds) s"

# Same vertex and face counts as alone, closed, one component, within 1e-6 of the diagonal.
check_mesh() {
  local run=$1 status=$2 address=$3 id=$4 report hausdorff diagonal
  for s in vertices triangles components boundary_edges; do
    [[ $(stat_of "$status" $s) == $(stat_of "$alone" $s) ]] ||
      fail "$run: $s $(stat_of "$status" $s), alone $(stat_of "$alone" $s)"
  done
  client "$address" fetch "$id" -o "$work/$run.ply"
  report=$("$bin/lsqsurf" compare "$work/alone.ply" "$work/$run.ply" --samples 200000)
  hausdorff=$(awk '$1 == "hausdorff" {print $2}' <<<"$report")
  diagonal=$(awk '$1 == "diagonal" {print $2}' <<<"$report")
  awk -v h="$hausdorff" -v d="$diagonal" 'BEGIN {exit !(h <= 1e-6 * d)}' ||
    fail "$run: the mesh is $hausdorff from the lone server's (diagonal $diagonal)"
  echo "netns-replicas: $run: $(stat_of "$status" vertices) vertices, Hausdorff $hausdorff to the lone server's" \
    "(diagonal $diagonal), $(stat_of "$status" wall_seconds) s"
}

for i in 0 1 2; do start_replica "$i"; done
# Nothing but the links joins them: a replica cannot reach another one.
if ip netns exec "lsq$tag-r0" "$bin/lsqsurf" --plaintext --server "$(replica_address 1)" health --timeout 1 >/dev/null 2>&1; then
  fail "replica r0 reaches r1: the namespaces are not separate"
fi

# 1. A helper killed once both helpers have made tiles.
id=$(client "$(replica_address 0)" submit "${job[@]}")
wait_for 60 "job $id to start" coordinator_of "$(replica_address 0)" "$id" >/dev/null
coordinator=$(coordinator_of "$(replica_address 0)" "$id")
helpers=()
for i in 0 1 2; do ((i == coordinator)) || helpers+=("$i"); done
both_made() { (($(made_by "${helpers[0]}" "$id") > 0 && $(made_by "${helpers[1]}" "$id") > 0)); }
wait_for 120 "both helpers to make a tile of job $id" both_made
killed=${helpers[0]}
kill -9 "${pids[$killed]}"
wait "${pids[$killed]}" 2>/dev/null || true
unset "pids[$killed]"
status=$(wait_done "$(replica_address "$coordinator")" "$id")
[[ $(stat_of "$status" replicas) == 3 ]] || fail "helper run: replicas $(stat_of "$status" replicas), not 3"
[[ $(stat_of "$status" tiles) == "$tiles" ]] || fail "helper run: $(stat_of "$status" tiles) tiles, alone $tiles"
check_mesh helper-killed "$status" "$(replica_address "$coordinator")" "$id"
echo "netns-replicas: helper-killed: r$killed killed after $(made_by "$killed" "$id") tiles; replicas 3"
start_replica "$killed"

# 2. The coordinator killed once a third of the tiles are made.
id=$(client "$(replica_address 1)" submit "${job[@]}")
wait_for 60 "job $id to start" coordinator_of "$(replica_address 1)" "$id" >/dev/null
coordinator=$(coordinator_of "$(replica_address 1)" "$id")
third_made() { (($(tiles_made "$id") * 3 >= tiles)); }
wait_for 120 "a third of job $id's tiles" third_made
kill -9 "${pids[$coordinator]}"
wait "${pids[$coordinator]}" 2>/dev/null || true
unset "pids[$coordinator]"
survivor=$(((coordinator + 1) % 3))
status=$(wait_done "$(replica_address "$survivor")" "$id")
reused=$(stat_of "$status" reused_tiles)
[[ -n $reused ]] && ((reused > 0)) || fail "coordinator run: no tile reused (reused_tiles '$reused')"
[[ $(field_of "$status" attempts) == 2 ]] || fail "coordinator run: attempts $(field_of "$status" attempts), not 2"
check_mesh coordinator-killed "$status" "$(replica_address "$survivor")" "$id"
echo "netns-replicas: coordinator-killed: r$coordinator killed; taken over by $(field_of "$status" runner)," \
  "$reused of $tiles tiles reused"
start_replica "$coordinator"

# 3. A server of another build joins while the job runs: it leaves the tiles alone. It is
# stopped before the job is submitted and comes back once the job runs, so that it neither
# coordinates the job nor has made tiles of it before.
other=2
kill -TERM "${pids[$other]}"
wait "${pids[$other]}" 2>/dev/null || true
unset "pids[$other]"
id=$(client "$(replica_address 0)" submit "${job[@]}")
wait_for 60 "job $id to start" coordinator_of "$(replica_address 0)" "$id" >/dev/null
coordinator=$(coordinator_of "$(replica_address 0)" "$id")
start_replica "$other" --tile-format 99
status=$(wait_done "$(replica_address "$coordinator")" "$id")
(($(made_by "$other" "$id") == 0)) || fail "build run: the server of another build made $(made_by "$other" "$id") tiles"
[[ $(stat_of "$status" replicas) == 2 ]] || fail "build run: replicas $(stat_of "$status" replicas), not 2"
check_mesh other-build "$status" "$(replica_address "$coordinator")" "$id"
echo "netns-replicas: other-build: r$other (tile format 99) made no tile; replicas 2"
echo "netns-replicas: passed"
