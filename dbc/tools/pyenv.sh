#!/bin/sh
# Prints the path of a python that has cantools, creating a venv for it on first use.
# The venv lives in $EXOCAL_PYENV (default: <workspace>/target/exocal-pyenv) so that tests run
# offline later (the vcan harness VM has no network: run this once on the host before).
# Fails loudly when python3 or PyPI is unavailable.
set -eu
root=$(cd "$(dirname "$0")/../.." && pwd)
venv=${EXOCAL_PYENV:-$root/target/exocal-pyenv}
if ! "$venv/bin/python" -c 'import cantools' >/dev/null 2>&1; then
    command -v python3 >/dev/null || { echo "pyenv.sh: python3 not found; it is needed for the cantools cross-checks" >&2; exit 1; }
    python3 -m venv "$venv" >&2
    "$venv/bin/pip" install --quiet 'cantools>=39' >&2
fi
echo "$venv/bin/python"
