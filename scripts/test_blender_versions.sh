#!/usr/bin/env bash
# `make test-blender-versions`: the Blender tests (pytest marker `blender`: Cycles
# references, the Defocus node, blender_compat, the extension installed in a fresh
# Blender, `mpib render --engine cycles`) on every environment of
# scripts/blender-versions.txt (bpy 4.2 LTS, 4.5 LTS, the newest 5.x), each built on
# first use by scripts/setup_blender_env.sh. Tests marked `slow` are left out, as in
# `make test`. Runs every version even when one fails, then prints one line per version
# and exits 1 if any failed (2 if an environment could not be built).
# Usage: scripts/test_blender_versions.sh [NAME...] [-- PYTEST_ARGS...]
set -uo pipefail
cd "$(dirname "$0")/.."
names=()
while [ $# -gt 0 ] && [ "$1" != "--" ]; do names+=("$1"); shift; done
[ "${1:-}" = "--" ] && shift
[ ${#names[@]} -gt 0 ] || mapfile -t names < <(grep -vE '^[[:space:]]*(#|$)' scripts/blender-versions.txt | awk '{print $1}')
summary=()
status=0
for name in "${names[@]}"; do
  if ! bash scripts/setup_blender_env.sh "$name"; then
    summary+=("$name: environment could not be built")
    status=2
    continue
  fi
  version=$(".venv-$name/bin/python" -c 'import bpy; print(bpy.app.version_string)' 2>/dev/null | tail -n 1)
  echo "=== $name: bpy $version"
  log=$(mktemp)
  ".venv-$name/bin/python" -m pytest -m "blender and not slow" -q -p no:cacheprovider "$@" 2>&1 | tee "$log"
  rc=${PIPESTATUS[0]}
  result=$(grep -E '^(=+ )?[0-9]+ (passed|failed|error)' "$log" | tail -n 1 | sed 's/=//g; s/^ *//; s/ *$//')
  rm -f "$log"
  summary+=("$name (bpy $version): ${result:-no result} (exit $rc)")
  [ "$rc" = 0 ] || { [ "$status" = 0 ] && status=1; }
done
echo "=== Blender versions"
printf '%s\n' "${summary[@]}"
exit $status
