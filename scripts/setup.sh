#!/usr/bin/env bash
# Builds the project's virtual environment with pinned versions.
# Usage: scripts/setup.sh [python] [venv-dir]
set -euo pipefail
PY=${1:-python3.11}
VENV=${2:-.venv}
cd "$(dirname "$0")/.."

# Dr.Jit's LLVM backend needs libLLVM >= 16. Debian's libllvm19 works; install it
# when we can (root + apt). Without it the ray tracer falls back to numpy.
if ! ls /usr/lib/*/libLLVM*.so* 2>/dev/null | grep -qE 'LLVM(-|\.so\.)(1[6-9]|[2-9][0-9])'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing libllvm19 for Dr.Jit's LLVM backend"
    (apt-get install -y -qq libllvm19 >/dev/null 2>&1 || \
      (apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq libllvm19 >/dev/null 2>&1)) || \
      echo "setup: could not install libllvm19; Dr.Jit will fall back to numpy"
  else
    echo "setup: no libLLVM >= 16 and no apt as root; Dr.Jit will fall back to numpy"
  fi
fi

"$PY" -c 'import sys; assert sys.version_info[:2] == (3, 11), "Python 3.11 is required, got %s" % sys.version' 
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --disable-pip-version-check --upgrade "pip==25.2"
"$VENV/bin/python" -m pip install -q --disable-pip-version-check "setuptools==80.9.0" "wheel==0.45.1"
"$VENV/bin/python" -m pip install -q --disable-pip-version-check -c constraints.txt -e ".[all]"
# the Blender extension's bundled wheels (OpenEXR, SciPy; cp311 and cp313 for Linux,
# Windows and both Macs: 14 files, 252 MB), fetched now so that building the
# platform zips later (make addon, the add-on tests, which build and check all four)
# needs no network
"$VENV/bin/python" scripts/build_addon.py --fetch-only
echo "setup: environment ready in $VENV"
