#!/usr/bin/env bash
# The main job, end to end on a fresh Debian 12 machine: install dependencies, build, start a springblend
# server on loopback with a cache directory, upload the bundled rigs (the cylinder and the ICT face), solve a
# 36-frame cylinder sweep with an obstacle (the paper's protocol) and a jaw opening on the server into out/,
# solve the cylinder locally for comparison, and stop the server.
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/install-deps.sh
cmake --preset release >/dev/null
cmake --build --preset release -j "$(nproc)" --target springblend springblend-server
bin=build/release
data=tests/data/cylinder
mkdir -p out
rm -rf out/frames out/local out/face

"$bin/server/springblend-server" --listen 127.0.0.1:0 --cache-dir out/cache >out/server.address 2>out/server.log &
server=$!
trap 'kill -TERM $server 2>/dev/null; wait $server 2>/dev/null || true' EXIT
for _ in $(seq 100); do grep -q "listening on" out/server.address 2>/dev/null && break; sleep 0.1; done
address=$(sed -n 's/.*listening on //p' out/server.address)
echo "server on $address (log: out/server.log)"
"$bin/client/springblend" health --server "$address"

echo "uploading the example rig: the cylinder, bending and twisting targets"
"$bin/client/springblend" upload --server "$address" --rest "$data/cylinder.obj" \
  --target "$data/poses-2_cylinder-1.obj" --target "$data/poses-2_cylinder-3.obj" --name cylinder | tee out/character.json
id=$(sed -n 's/.*"id":"\([0-9a-f]*\)".*/\1/p' out/character.json)

echo "solving 36 frames on the server into out/frames/"
"$bin/client/springblend" solve --server "$address" --character "$id" --sweep 36 --weights 0.8,0.4 \
  --collider sphere:-1.7,0.75,0.75,0.3 --out out/frames >out/frames.jsonl
awk 'NR % 6 == 0' out/frames.jsonl

echo "uploading the bundled face rig (ICT neutral and jawOpen) and solving a 3-frame jaw opening into out/face/"
"$bin/client/springblend" upload --server "$address" --rest tests/data/face/generic_neutral_mesh.obj \
  --target tests/data/face/jawOpen.obj --name ict-face | tee out/face.json
face=$(sed -n 's/.*"id":"\([0-9a-f]*\)".*/\1/p' out/face.json)
"$bin/client/springblend" solve --server "$address" --character "$face" --sweep 3 --out out/face | tee out/face.jsonl

echo "the same cylinder frames solved locally, for comparison, into out/local/"
"$bin/client/springblend" blend --rest "$data/cylinder.obj" --target "$data/poses-2_cylinder-1.obj" \
  --target "$data/poses-2_cylinder-3.obj" --sweep 36 --weights 0.8,0.4 --collider sphere:-1.7,0.75,0.75,0.3 \
  --out out/local >out/local.jsonl
echo "wrote out/frames/frame_0000.obj .. frame_0035.obj and out/face/ (server), out/local/ (local), out/*.jsonl"
echo "(summaries)"
