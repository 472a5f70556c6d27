#!/usr/bin/env bash
# Installs what it needs into ./.venv, then runs the main job on the embedded default input. The job runs in the
# caller's folder: `--out` and the default ./torchface-demo/ are the caller's, as for `torchface demo` itself.
caller=$PWD
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
root=$PWD
cd "$caller"
exec "$root/.venv/bin/torchface" demo "$@"
