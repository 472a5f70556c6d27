# Sourced by demo.sh and test.sh: creates ./.venv and installs torchface into it (CPU torch pinned first).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PY="${PYTHON:-python3.11}"
command -v "$PY" >/dev/null 2>&1 || PY=python3
if [ ! -x .venv/bin/python ]; then
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
