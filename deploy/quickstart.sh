#!/usr/bin/env bash
# The main job, end to end on a fresh Debian 12 machine: install dependencies, build, and solve the bundled
# example rig (the cylinder bending, 36 warm-started frames, the paper's protocol) into out/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/install-deps.sh
cmake --preset release >/dev/null
cmake --build --preset release -j "$(nproc)" --target springblend
bin=build/release/client/springblend
data=tests/data/cylinder
mkdir -p out
echo "solving 36 frames of ${data}/cylinder.obj -> poses-2_cylinder-1.obj into out/sweep/ (one JSON line per frame)"
"$bin" blend --rest "$data/cylinder.obj" --target "$data/poses-2_cylinder-1.obj" --sweep 36 --out out/sweep \
  | tee out/sweep.jsonl | awk 'NR % 6 == 0'
"$bin" blend --rest "$data/cylinder.obj" --target "$data/poses-2_cylinder-1.obj" --sweep 36 --out out/linear \
  --linear >/dev/null
echo "wrote out/sweep/frame_0000.obj .. frame_0035.obj (physical) and out/linear/ (linear blendshape, for comparison)"
