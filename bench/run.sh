#!/usr/bin/env bash
# The benchmark in one command: installs the dependencies (Debian 12), builds the bench configuration, runs
# springblend-bench (the paper's Table 1 protocol on every row whose meshes are present) and the service
# throughput script, and writes bench-results/{bench.md,bench.json,ms_per_step.png,service.md}.
#   bash bench/run.sh [springblend-bench options, e.g. --rows face,horse --steps 36]
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/install-deps.sh
cmake -S . -B build/bench -G Ninja -DCMAKE_BUILD_TYPE=Release -DSPRINGBLEND_BUILD_BENCH=ON \
  -DSPRINGBLEND_BUILD_TESTS=OFF > /dev/null
cmake --build build/bench --target springblend-bench springblend springblend-server -j "$(nproc)"
status=0
build/bench/bench/springblend-bench --out bench-results "$@" || status=$?
bash bench/service.sh build/bench bench-results
exit "$status"
