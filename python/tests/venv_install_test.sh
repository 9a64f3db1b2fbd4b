#!/usr/bin/env bash
# The README's install command works: a fresh virtual environment over Debian's Python, the package
# installed from the checkout with pip offline, then a real job through the installed package.
# Usage: venv_install_test.sh CHECKOUT BUILD_DIR LSQSURFD
set -euo pipefail
checkout=$1 build_dir=$2
export LSQSURFD=$3
work=$(mktemp -d)
trap 'rm -rf "$work" "$checkout/python/build" "$checkout"/python/*.egg-info' EXIT
/usr/bin/python3 -m venv --system-site-packages "$work/venv"
LSQSURF_BUILD_DIR="$build_dir" "$work/venv/bin/pip" install --no-build-isolation --no-index -q "$checkout/python"
cd "$work"  # Not the checkout: the package must come from the environment.
"$work/venv/bin/python" - <<'PY'
import lsqsurf
assert "/venv/" in lsqsurf.__file__, lsqsurf.__file__
PY
"$work/venv/bin/python" -m pytest -q -p no:cacheprovider "$checkout/python/tests/test_client.py" \
  -k "closed_sphere or bad_keywords"
