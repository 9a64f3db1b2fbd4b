#!/usr/bin/env bash
# The main job on a fresh Debian 12 machine: install what is needed, build, start lsqsurfd on
# loopback, reconstruct the bundled sample cloud with the client, and write the mesh and a
# picture of it to out/.
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/install-deps.sh
cmake --preset release >/dev/null
cmake --build --preset release --target lsqsurfd lsqsurf

bin=build/release/bin
mkdir -p out
data_dir=$(mktemp -d)
log=out/lsqsurfd.log
# Port 0: the server picks a free port and prints it on its first stdout line.
coproc SERVER { exec "$bin/lsqsurfd" --listen 127.0.0.1:0 --data-dir "$data_dir" 2>"$log"; }
trap 'kill -TERM "$SERVER_PID" 2>/dev/null || true; wait "$SERVER_PID" 2>/dev/null || true; rm -rf "$data_dir"' EXIT
read -r -t 30 line <&"${SERVER[0]}"
address=${line#listening on }
echo "lsqsurfd is listening on $address (log: $log)"

"$bin/lsqsurf" --server "$address" reconstruct samples/spot-30k.ply -o out/spot.ply -o out/spot.drc \
  --preview out/spot.png --up y --azimuth 215
