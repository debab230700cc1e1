#!/usr/bin/env bash
# Builds one extra Blender test environment, .venv-<name>, from scripts/blender-versions.txt:
# its Python (3.11 or 3.13), the pinned bpy and numpy, and the project (editable) with
# what the Blender tests need (test, generate, metrics, cli extras), every other version
# from constraints.txt. Idempotent: a finished environment has a stamp and is kept.
# Usage: scripts/setup_blender_env.sh NAME    (e.g. bpy42, bpy45, bpy5x)
# The interpreters: $PY311 / $PY313 if set, else python3.11 / python3.13 on PATH, else
# pyenv's (the machine's pyenv has 3.13 without putting it on PATH).
set -euo pipefail
cd "$(dirname "$0")/.."
NAME=${1:?usage: setup_blender_env.sh NAME}
line=$(grep -E "^$NAME[[:space:]]" scripts/blender-versions.txt || true)
if [ -z "$line" ]; then
  echo "setup_blender_env: no environment '$NAME' in scripts/blender-versions.txt" >&2
  exit 2
fi
read -r _ PYVER BPY NUMPY <<<"$line"
VENV=.venv-$NAME
# the stamp names what the environment was built from: its line, the pins, the extras
KEY=$( (echo "$line"; cat constraints.txt pyproject.toml) | sha256sum | cut -c1-16)
STAMP=$VENV/.installed-$KEY
[ -f "$STAMP" ] && { echo "setup_blender_env: $VENV ready (bpy $BPY)"; exit 0; }

find_python() {  # find_python 3.13 -> an interpreter of exactly that version
  local v=$1 var="PY${1/./}" cand
  for cand in "${!var:-}" "python$v" "$(pyenv root 2>/dev/null)"/versions/"$v"*/bin/"python$v" \
              "$HOME"/.pyenv/versions/"$v"*/bin/"python$v"; do
    [ -n "$cand" ] || continue
    if "$cand" -c "import sys; assert sys.version_info[:2] == ($v_tuple)" 2>/dev/null; then
      echo "$cand"; return 0
    fi
  done
  return 1
}
v_tuple=${PYVER/./, }
PY=$(find_python "$PYVER") || {
  echo "setup_blender_env: Python $PYVER not found (set PY${PYVER/./}=/path/to/python$PYVER)" >&2
  exit 2
}
echo "setup_blender_env: $VENV with $PY, bpy $BPY, numpy $NUMPY"
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
PIP=("$VENV/bin/python" -m pip install -q --disable-pip-version-check)
"${PIP[@]}" "pip==25.2" "setuptools==80.9.0" "wheel==0.45.1"
# constraints.txt without its bpy and numpy lines (this environment pins its own)
CONS=$(mktemp)
trap 'rm -f "$CONS"' EXIT
grep -vE '^(bpy|numpy)==' constraints.txt >"$CONS"
echo "numpy==$NUMPY" >>"$CONS"
"${PIP[@]}" -c "$CONS" "bpy==$BPY" "numpy==$NUMPY"
"${PIP[@]}" -c "$CONS" -e ".[test,generate,metrics,cli,report]"
"$VENV/bin/python" -c "import bpy, numpy; assert bpy.app.version_string.startswith('${BPY%.*}'), bpy.app.version_string; print('setup_blender_env: bpy', bpy.app.version_string, 'numpy', numpy.__version__)"
# the extension's bundled wheels (cp311 and cp313, every platform), so that the add-on
# tests build offline
"$VENV/bin/python" scripts/build_addon.py --fetch-only
rm -f "$VENV"/.installed-*
touch "$STAMP"
