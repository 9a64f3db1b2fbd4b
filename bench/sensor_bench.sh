#!/usr/bin/env bash
# Simulated sensors on known meshes, through a server with defaults, measured against the truth.
#
#   bench/sensor_bench.sh [MESH ...]     (default: the shared meshes)
#
# For each mesh: a depth camera's single view (PCD with its VIEWPOINT), four merged depth views
# and a four-station terrestrial lidar (PTX with each sensor's position and 0.1 % registration
# error), each reconstructed with PU and iaMLS; a clean sample of the same size with PU for the
# time it costs on a clean cloud; the merged views and the lidar again with fill_holes=true, whose
# rows add watertight and the marked area's precision and recall against the unmeasured area
# (filled_precision: the share of the marked area farther than 3 local spacings from every point;
# filled_recall: the share of that area marked; the _global pair uses the scan's one median
# spacing instead); the clean sample again with fill_holes=true, whose filled_marked is the share
# a closed, evenly sampled cloud gets marked by chance. Prints one row per run: wall time, the report's measures
# (bench/sensor_sim.cc: facing, components, fragments, boundary edges, invented and covered
# shares, mean distance to the truth, Chamfer distance to it, colour error). Where python3-open3d is installed
# (install-deps.sh --with-poisson), screened Poisson rows follow each scan's (P0: watertight,
# P0.1: trimmed below the 10 % density quantile; their wall is Poisson's own time), given the
# normals a job gives the scan. Needs a release build with Embree (lsqsurf-sensor-sim). Leaves its files in $WORK (default a temporary folder).
set -euo pipefail
cd "$(dirname "$0")/.."
bin=build/release/bin
python=${PYTHON:-/usr/bin/python3}  # Debian's, where apt puts python3-open3d
work=${WORK:-$(mktemp -d)}
mkdir -p "$work"
meshes=("$@")
if [[ ${#meshes[@]} -eq 0 ]]; then
  shared=${SHARED_MESHES:-../shared/data/meshes}
  meshes=("$shared"/stanford-bunny.obj "$shared"/spot.obj "$shared"/homer.obj "$shared"/fandisk.obj)
fi
port=$((20000 + RANDOM % 20000))
"$bin"/lsqsurfd --listen 127.0.0.1:$port --data-dir "$work/server" --workers 1 >"$work/server.log" 2>&1 &
server=$!
trap 'kill $server 2>/dev/null || true' EXIT
export LSQSURF_SERVER=127.0.0.1:$port
for _ in $(seq 50); do "$bin"/lsqsurf -q methods >/dev/null 2>&1 && break; sleep 0.2; done

run() {  # run NAME MESH SCAN METHOD [PARAM ...]
  local name=$1 mesh=$2 scan=$3 method=$4 out="$work/$1.$4.ply" log="$work/$1.$4.log" start end params=()
  shift 4
  for p in "$@"; do params+=(--param "$p"); done
  start=$(date +%s.%N)
  "$bin"/lsqsurf -q reconstruct "$scan" -o "$out" --method "$method" "${params[@]}" >"$log" 2>&1 || {
    echo "$name $method FAILED: $(tail -1 "$log")"; return; }
  end=$(date +%s.%N)
  printf '%-28s %-6s wall %6.1f s  ' "$name" "$method" "$(echo "$end - $start" | bc)"
  report "$mesh" "${reference:-$scan}" "$out"
}

report() {  # report MESH SCAN RECONSTRUCTION
  "$bin"/lsqsurf-sensor-sim report --truth "$1" --scan "$2" --mesh "$3" |
    awk '{printf "%s %s  ", $1, $2} END {print ""}'
}

# Screened Poisson (depth 10) on the same scan with the normals a job gives it: watertight, and
# trimmed below the 10 % density quantile. Only where python3-open3d is installed.
poisson() {  # poisson NAME MESH SCAN
  local name=$1 mesh=$2 scan=$3 points="$work/$1.oriented.ply" trim out
  "$python" -c 'import open3d' 2>/dev/null || return 0
  "$bin"/lsqsurf-sensor-sim prepare "$scan" -o "$points" >/dev/null || { echo "$name prepare FAILED"; return; }
  for trim in 0 0.1; do
    out="$work/$name.poisson-$trim.ply"
    seconds=$("$python" bench/poisson_reference.py "$points" -o "$out" --trim $trim | awk '$1 == "poisson_seconds" {print $2}') ||
      { echo "$name poisson FAILED"; continue; }
    printf '%-28s %-6s wall %6.1f s  ' "$name" "P$trim" "$seconds"
    report "$mesh" "$scan" "$out"
  done
}

for mesh in "${meshes[@]}"; do
  base=$(basename "$mesh" .obj)
  "$bin"/lsqsurf-sensor-sim depth "$mesh" -o "$work/$base.view.pcd" 2>/dev/null
  "$bin"/lsqsurf-sensor-sim depth "$mesh" --views 4 -o "$work/$base.views.ptx" 2>/dev/null
  "$bin"/lsqsurf-sensor-sim lidar "$mesh" -o "$work/$base.lidar.ptx" 2>/dev/null
  points=$("$bin"/lsqsurf-sensor-sim report --truth "$mesh" --scan "$work/$base.view.pcd" --mesh "$mesh" |
    awk '$1 == "scan_points" {print $2}')
  "$bin"/lsqsurf sample "$mesh" -o "$work/$base.clean.ply" --points "$points" >/dev/null
  run "$base.clean-$points" "$mesh" "$work/$base.clean.ply" pu
  run "$base.clean-$points.filled" "$mesh" "$work/$base.clean.ply" pu fill_holes=true
  for scan in view.pcd views.ptx lidar.ptx; do
    for method in pu iamls; do run "$base.$scan" "$mesh" "$work/$base.$scan" $method; done
    poisson "$base.$scan" "$mesh" "$work/$base.$scan"
  done
  for scan in views.ptx lidar.ptx; do
    for method in pu iamls; do run "$base.$scan.filled" "$mesh" "$work/$base.$scan" $method fill_holes=true; done
  done
done
# A room in one stereo view (bench/room_scene.py): disparity steps of 0.004 of the diagonal at the
# centre's distance, each many spacings wide, undone by default and left with
# undo_depth_steps=false. The report measures covered
# and invented against the view without steps: the steps put points up to half a step, about 15
# spacings, off the surface.
room="$work/room.obj"
if "$python" bench/room_scene.py "$room" --meshes "${SHARED_MESHES:-../shared/data/meshes}" >/dev/null 2>&1; then
  sim=("$bin"/lsqsurf-sensor-sim depth "$room" --eye 0,1.2,2.2 --up 0,1,0)
  "${sim[@]}" --quantum 0 -o "$work/room.view.pcd" 2>/dev/null
  "${sim[@]}" --quantum 0.004 -o "$work/room.stereo.pcd" 2>/dev/null
  for method in pu iamls; do
    run room.view "$room" "$work/room.view.pcd" $method
    reference="$work/room.view.pcd" run room.stereo "$room" "$work/room.stereo.pcd" $method
    reference="$work/room.view.pcd" run room.stereo.steps-left "$room" "$work/room.stereo.pcd" $method \
      undo_depth_steps=false
  done
fi
echo "files in $work"
