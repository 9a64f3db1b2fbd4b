#!/usr/bin/env bash
# The whole test suite: the style gates (scripts/check-style.sh), then an optimised build and an
# AddressSanitizer + UndefinedBehaviorSanitizer build, each followed by ctest. Installs missing
# packages first. CI runs exactly this.
set -euo pipefail
cd "$(dirname "$0")/.."

bash scripts/install-deps.sh
bash scripts/check-style.sh

# Compiler cache entries keyed by paths relative to the checkout, so that a fresh clone in
# another folder (CI's) reuses what an earlier build compiled.
export CCACHE_BASEDIR="$PWD" CCACHE_NOHASHDIR=true

cmake --preset release
cmake --build --preset release
ctest --preset release

# The sanitizer build skips the benchmarks and the tests labelled `slow`.
cmake --preset asan
cmake --build --preset asan
ctest --preset asan
