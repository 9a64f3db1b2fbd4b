#!/usr/bin/env bash
# Style gates the test command runs: every C++ source formatted as .clang-format says, no
# function in the product longer than 120 lines, and no include the layering forbids
# (scripts/layering.py, which also holds files to 800 lines and refuses friend, shared_ptr<void> and
# another module's internals). Fix formatting with: scripts/check-style.sh --fix
set -euo pipefail
cd "$(dirname "$0")/.."

mapfile -t sources < <(git ls-files -- '*.cc' '*.h' | grep -v '^third_party/')
if [[ "${1:-}" == "--fix" ]]; then
  clang-format -i "${sources[@]}"
fi
clang-format --dry-run --Werror "${sources[@]}"
python3 scripts/function_lengths.py --limit 120 worker server client python bench
python3 scripts/layering.py
echo "check-style: ${#sources[@]} files formatted, no function over 120 lines, layering and shape rules hold"
