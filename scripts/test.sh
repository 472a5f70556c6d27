#!/usr/bin/env bash
# Installs what it needs into ./.venv, then runs the test suite.
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
exec .venv/bin/python -m pytest -q "$@"
