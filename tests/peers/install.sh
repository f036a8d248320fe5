#!/usr/bin/env bash
# Installs the pinned Python peers (tests/peers/requirements.txt) into
# target/peers-venv, once per change of the requirements. The tests find the
# interpreter at target/peers-venv/bin/python; with CI set, a test whose peer is
# missing fails instead of skipping.
set -euo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
venv=$root/target/peers-venv
req=$root/tests/peers/requirements.txt
stamp=$venv/.requirements
if [[ -x $venv/bin/python ]] && cmp -s "$req" "$stamp"; then
    exit 0
fi
echo "== installing the Python test peers into target/peers-venv"
python3 -m venv "$venv"
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$req"
cp "$req" "$stamp"
