#!/usr/bin/env bash
# Fuzzes every parser and decoder that sees client bytes with libFuzzer (clang from Debian):
# PLY, PCD, OBJ, XYZ, legacy VTK volumes, VTU, the velocity grid, the Draco wrapper, the uploads as
# the job service checks them, and the proto-to-spec conversion.
#
#   scripts/fuzz.sh [SECONDS] [TARGET...]   SECONDS per target (default 60); all targets by default
#   scripts/fuzz.sh --seeds                  rewrite tests/fuzz/seeds from the project's writers
#
# Builds the `fuzz` preset (clang, ASan + UBSan + libFuzzer), runs each target from its seeds
# (tests/fuzz/seeds/TARGET) and its saved regressions (tests/fuzz/regressions/TARGET) with a
# working corpus in build/fuzz/corpus/TARGET, two targets at a time (one per core), and prints
# per target the executions, their rate, the corpus and the coverage reached. A crash or leak
# leaves its input in build/fuzz/crashes/TARGET and fails the script: copy it to
# tests/fuzz/regressions/TARGET, where the ordinary test suite replays it (ctest fuzz_replay_*).
set -euo pipefail
cd "$(dirname "$0")/.."

targets_all=(ply pcd las ptx obj xyz vtk_volume vtu velocity_grid draco uploads job_spec)

bash scripts/install-deps.sh --with-fuzz >/dev/null
cmake --preset fuzz >/dev/null
cmake --build --preset fuzz

if [[ ${1:-} == --seeds ]]; then
  rm -rf tests/fuzz/seeds
  build/fuzz/bin/make_seeds tests/fuzz/seeds
  exit 0
fi

seconds=${1:-60}
shift || true
targets=("$@")
((${#targets[@]})) || targets=("${targets_all[@]}")

work=build/fuzz
mkdir -p "$work/logs"
run_one() {
  local t=$1
  mkdir -p "$work/corpus/$t" "$work/crashes/$t" "tests/fuzz/regressions/$t"
  # Files other programs wrote (tests/data/TARGET, where there are any) seed it too.
  local elsewhere=()
  [[ -d tests/data/$t ]] && elsewhere=("tests/data/$t")
  # rss_limit bounds a run's memory (a decoder asked to allocate far too much counts as a bug);
  # -timeout flags an input that takes longer than 10 s.
  "$work/bin/fuzz_$t" -max_total_time="$seconds" -rss_limit_mb=2048 -timeout=10 -print_final_stats=1 \
    -artifact_prefix="$work/crashes/$t/" "$work/corpus/$t" "tests/fuzz/seeds/$t" "tests/fuzz/regressions/$t" \
    "${elsewhere[@]}" >"$work/logs/$t.log" 2>&1
}

status=0
pids=()
names=()
for t in "${targets[@]}"; do
  run_one "$t" &
  pids+=($!)
  names+=("$t")
  if ((${#pids[@]} == 2)); then
    wait "${pids[0]}" || status=1
    pids=("${pids[@]:1}")
  fi
done
for p in "${pids[@]}"; do wait "$p" || status=1; done

printf '%-14s %12s %10s %8s %8s %s\n' target executions exec/s corpus cov result
for t in "${names[@]}"; do
  log=$work/logs/$t.log
  runs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1)
  rate=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$log" | tail -1)
  corpus=$(find "$work/corpus/$t" -type f | wc -l)
  cov=$(grep -o 'cov: [0-9]*' "$log" | tail -1 | cut -d' ' -f2)
  crashes=$(find "$work/crashes/$t" -type f | wc -l)
  result=ok
  ((crashes == 0)) || result="$crashes crash(es): $work/crashes/$t"
  grep -q "ERROR: libFuzzer\|ERROR: AddressSanitizer\|ERROR: LeakSanitizer\|runtime error" "$log" && result="failed: $log"
  printf '%-14s %12s %10s %8s %8s %s\n' "$t" "${runs:-?}" "${rate:-?}" "$corpus" "${cov:-?}" "$result"
done
exit $status
