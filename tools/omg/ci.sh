#!/usr/bin/env bash
# CI for the OMG data generator: install the pinned requirements, run the tests.
# Usage (from anywhere): bash tools/omg/ci.sh
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
python3 -m pip install -q --disable-pip-version-check -r "$here/requirements-data.txt"
cd "$root"
python3 -m pytest -q -p no:cacheprovider tools/omg/tests
