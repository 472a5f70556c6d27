# Sourced by demo.sh and test.sh: creates ./.venv and installs torchface into it (CPU torch pinned first).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
# Python 3.11 only: the pinned torch below is the CPU build for CPython 3.11; under another Python, pip would look
# for another build of it (on PyPI, one that pulls several GB of CUDA packages) or find none.
_is_py311() { "$1" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' >/dev/null 2>&1; }
if [ -n "${PYTHON:-}" ]; then
  PY=$PYTHON
  _is_py311 "$PY" || { echo "[setup] error: PYTHON=$PY is not Python 3.11" >&2; exit 1; }
else
  PY=
  for candidate in python3.11 python3; do
    if command -v "$candidate" >/dev/null 2>&1 && _is_py311 "$candidate"; then
      PY=$candidate
      break
    fi
  done
  if [ -z "$PY" ]; then
    echo "[setup] error: Python 3.11 is needed: neither python3.11 nor python3 on the PATH is Python 3.11" \
      "(python3: $(python3 --version 2>&1 || true)); install it, or set PYTHON=/path/to/python3.11" >&2
    exit 1
  fi
fi
# A .venv made in another folder (moved or copied with the repository: its scripts and editable install still run
# that folder's code), as venv's pyvenv.cfg records it.
_made_here() {
  here=" $(pwd -P)/.venv" awk 'index($0, "command = ") == 1 { made = 1; n = length(ENVIRON["here"])
    if (substr($0, length($0) - n + 1) == ENVIRON["here"]) here = 1 } END { exit made && !here }' .venv/pyvenv.cfg
}
# A .venv whose creation was interrupted (no working pip), made by another Python or elsewhere is made again.
if [ -e .venv ] || [ -L .venv ]; then
  if ! { _is_py311 .venv/bin/python && .venv/bin/python -m pip --version >/dev/null 2>&1; }; then
    echo "[setup] .venv is incomplete or not Python 3.11: making it again" >&2
    "$PY" -m venv --clear .venv
  elif ! _made_here; then
    echo "[setup] .venv was made in another folder (moved or copied here): making it again" >&2
    "$PY" -m venv --clear .venv
  fi
else
  "$PY" -m venv .venv
fi
stamp=.venv/.torchface-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "[setup] installing torchface into .venv (first run only)" >&2
  .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip
  # The pinned CPU wheel first: an unpinned torch would pull several GB of CUDA packages.
  .venv/bin/python -m pip install -q --disable-pip-version-check "torch==2.13.0"
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[dev]"
  touch "$stamp"
fi
