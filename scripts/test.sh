#!/usr/bin/env bash
# Installs what it needs into ./.venv, then runs the test suite.
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
# On every core (pytest-xdist: one worker per core, 8 at most; 5-6 minutes on 2 cores instead of 10-12); `-n 0`
# runs the tests in this one process. GNU OpenMP threads that wait for work sleep instead of spinning (the workers'
# torch threads outnumber the cores); it changes no result.
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
exec .venv/bin/python -m pytest -q -n auto --maxprocesses=8 "$@"
