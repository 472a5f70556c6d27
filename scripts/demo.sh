#!/usr/bin/env bash
# Installs what it needs into ./.venv, then runs the main job on the embedded default input.
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
exec .venv/bin/torchface demo "$@"
