#!/usr/bin/env bash
# Builds springblend and runs every test. Installs its own dependencies (Debian 12), works from a fresh clone.
#   bash tests/run.sh             release build + all tests
#   PRESET=asan-ubsan bash tests/run.sh   the same under AddressSanitizer + UndefinedBehaviorSanitizer
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/install-deps.sh
preset="${PRESET:-release}"
cmake --preset "$preset"
cmake --build --preset "$preset" -j "$(nproc)"
ctest --preset "$preset" -j "$(nproc)"
