#!/usr/bin/env bash
# Print the path of a Python >= 3.12 (LeRobot 0.5+ needs it): $PYTHON, then python3.12/3.13/3 on PATH,
# then pyenv's installs (a pyenv shim can exist for a version that is not the active one).
ok() { "$1" -c 'import sys; sys.exit(sys.version_info < (3, 12))' >/dev/null 2>&1; }
for p in "${PYTHON:-}" python3.12 python3.13 python3; do
  [ -n "$p" ] && command -v "$p" >/dev/null 2>&1 && ok "$p" && { command -v "$p"; exit 0; }
done
for p in "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.1[2-9]*/bin/python3; do
  [ -x "$p" ] && ok "$p" && { echo "$p"; exit 0; }
done
echo "No Python >= 3.12 found: install one (e.g. 'pyenv install 3.12') or set PYTHON=/path/to/python3.12" >&2
exit 1
