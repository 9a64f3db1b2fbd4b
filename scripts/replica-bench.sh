#!/usr/bin/env bash
# Throughput and call latency of lsqsurfd replicas behind nginx, all on loopback: starts a
# throwaway PostgreSQL (or none, with --store sqlite and one replica), N replicas and nginx,
# runs bench/lsqsurf-load through nginx, then stops everything.
#
#   scripts/replica-bench.sh [--replicas N] [--store postgresql|sqlite] [--workers W] -- LOAD-OPTIONS
#   scripts/replica-bench.sh --replicas 3 -- --cloud ../shared/data/meshes/stanford-bunny.obj \
#       --points 100000 --method iamls --jobs 30 --submitters 3 --pollers 4
#
# Needs a release build (cmake --preset release && cmake --build --preset release) and the
# packages of scripts/install-deps.sh (postgresql, nginx-light).
set -euo pipefail
cd "$(dirname "$0")/.."

replicas=1
store=postgresql
workers=1
while (($#)); do
  case "$1" in
    --replicas) replicas=$2; shift 2 ;;
    --store) store=$2; shift 2 ;;
    --workers) workers=$2; shift 2 ;;
    --) shift; break ;;
    *) echo "replica-bench: unknown option $1 (see the header of this script)" >&2; exit 2 ;;
  esac
done
if [[ $store == sqlite && $replicas != 1 ]]; then
  echo "replica-bench: the SQLite store serves one replica; use --store postgresql for more" >&2
  exit 2
fi

bin=build/release/bin
pg_bin=$(ls -d /usr/lib/postgresql/*/bin | tail -1)
work=$(mktemp -d /tmp/lsqsurf-replica-bench.XXXXXX)
chmod 755 "$work"  # The postgres user must reach its folder inside.
pids=()
as_postgres=()
cleanup() {
  for pid in "${pids[@]}"; do kill "$pid" 2>/dev/null || true; done
  wait 2>/dev/null || true
  if [[ -f $work/pg/data/postmaster.pid ]]; then "${as_postgres[@]}" "$pg_bin/pg_ctl" -D "$work/pg/data" -m fast stop >/dev/null; fi
  rm -rf "$work"
}
trap cleanup EXIT

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }

store_flags=()
if [[ $store == postgresql ]]; then
  mkdir -p "$work/pg"
  if [[ $(id -u) -eq 0 ]]; then  # PostgreSQL refuses to run as root.
    chown postgres "$work/pg"
    as_postgres=(runuser -u postgres --)
  fi
  pg_port=$(free_port)
  "${as_postgres[@]}" "$pg_bin/initdb" -D "$work/pg/data" -A trust -U lsqsurf -E UTF8 --locale=C >/dev/null
  "${as_postgres[@]}" "$pg_bin/pg_ctl" -D "$work/pg/data" -l "$work/pg/server.log" -w \
    -o "-p $pg_port -k $work/pg -c listen_addresses=127.0.0.1 -c max_connections=200" start >/dev/null
  store_flags=(--store "postgresql://lsqsurf@127.0.0.1:$pg_port/postgres")
fi

upstreams=""
for ((i = 0; i < replicas; ++i)); do
  mkdir -p "$work/r$i"
  "$bin/lsqsurfd" --listen 127.0.0.1:0 --data-dir "$work/r$i" --name "r$i" --workers "$workers" \
    --max-queue 1000 "${store_flags[@]}" >"$work/r$i.out" 2>"$work/r$i.log" &
  pids+=($!)
  for _ in $(seq 100); do grep -q "listening on" "$work/r$i.out" 2>/dev/null && break; sleep 0.1; done
  address=$(sed -n 's/^listening on //p' "$work/r$i.out")
  [[ -n $address ]] || { echo "replica-bench: replica r$i did not start; see its log:" >&2; cat "$work/r$i.log" >&2; exit 1; }
  upstreams+="    server $address;"$'\n'
done

nginx_port=$(free_port)
mkdir -p "$work/nginx/temp"
chmod 777 "$work/nginx/temp"
cat >"$work/nginx/nginx.conf" <<EOF
daemon off;
worker_processes 1;
pid $work/nginx/nginx.pid;
error_log $work/nginx/error.log warn;
events {}
http {
  access_log off;
  client_body_temp_path $work/nginx/temp/body;
  proxy_temp_path $work/nginx/temp/proxy;
  fastcgi_temp_path $work/nginx/temp/fastcgi;
  uwsgi_temp_path $work/nginx/temp/uwsgi;
  scgi_temp_path $work/nginx/temp/scgi;
  upstream lsqsurfd {
$upstreams  }
  server {
    listen 127.0.0.1:$nginx_port http2;
    client_max_body_size 0;
    grpc_read_timeout 1h;
    grpc_send_timeout 1h;
    location / { grpc_pass grpc://lsqsurfd; }
  }
}
EOF
nginx -p "$work/nginx/" -c "$work/nginx/nginx.conf" &
pids+=($!)
for _ in $(seq 100); do "$bin/lsqsurf" --server "127.0.0.1:$nginx_port" health --timeout 1 >/dev/null 2>&1 && break; sleep 0.1; done

echo "replica-bench: $replicas replica(s), store $store, $workers worker(s) each, through nginx on 127.0.0.1:$nginx_port"
"$bin/lsqsurf-load" --server "127.0.0.1:$nginx_port" "$@"
