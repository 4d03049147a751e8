#!/usr/bin/env bash
# Builds the libFuzzer targets (the `fuzz` preset: clang, ASan + UBSan) and runs each for a bounded time on a
# seed corpus made from tests/data. Exits non-zero on any finding; crash inputs land in build/fuzz/findings/.
#   bash fuzz/run.sh                 every target, 30 s each, as many at once as there are cores (CI: 20 s)
#   FUZZ_SECONDS=3600 bash fuzz/run.sh mesh_loader_fuzzer    one target for an hour
# The corpora in build/fuzz/corpus/ grow between runs; delete them to start over from the seeds.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds="${FUZZ_SECONDS:-30}"
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
  targets=(mesh_loader_fuzzer upload_assembler_fuzzer solve_request_fuzzer frames_file_fuzzer take_file_fuzzer
           cache_file_fuzzer)
fi
bash deploy/install-deps.sh fuzz
cmake --preset fuzz >/dev/null
cmake --build --preset fuzz -j "${JOBS:-2}" --target "${targets[@]}" make_fuzz_seeds

out=build/fuzz
seeds="$out/seeds"
rm -rf "$seeds"
mkdir -p "$seeds"/{mesh_loader_fuzzer,upload_assembler_fuzzer,solve_request_fuzzer,frames_file_fuzzer,take_file_fuzzer} \
  "$seeds/cache_file_fuzzer" \
  "$out/findings"
# Mesh loader: a format byte (0 obj, 1 off, 2 stl; 3 ply with SPRINGBLEND_FUZZ_PLY=1, see mesh_loader_fuzzer.cc)
# then the file: the first lines of a test mesh, and a tetrahedron in each format. (Small seeds: OpenMesh is slow
# on large inputs under ASan.)
{ printf '\x00'; head -c 3000 tests/data/cylinder/cylinder.obj | grep -E '^(v|f) '; } > "$seeds/mesh_loader_fuzzer/cylinder-part.obj"
tet_v='0 0 0\n1 0 0\n0 1 0\n0 0 1\n'
{ printf '\x00'; printf 'v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 3 1 4\n'; } > "$seeds/mesh_loader_fuzzer/tet.obj"
{ printf '\x01'; printf "OFF\n4 4 0\n$tet_v"'3 0 2 1\n3 0 1 3\n3 1 2 3\n3 2 0 3\n'; } > "$seeds/mesh_loader_fuzzer/tet.off"
{ printf '\x01'; printf '# quads, colours\nCOFF 5 2 0\n0 0 0 1 0 0\n1 0 0 0 1 0 1\n1 1 0 0 0 1\n0 1 0 1 1 1\n0.5 2 1e-3 0 0 0\n4 0 1 2 3 255 0 0\n3 3 2 4 # tip\n'; } > "$seeds/mesh_loader_fuzzer/quads.off"
{ printf '\x03'; printf "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 4\nproperty list uchar int vertex_indices\nend_header\n$tet_v"'3 0 2 1\n3 0 1 3\n3 1 2 3\n3 2 0 3\n'; } > "$seeds/mesh_loader_fuzzer/tet.ply"
{ printf '\x02'; printf 'solid t\nfacet normal 0 0 -1\nouter loop\nvertex 0 0 0\nvertex 0 1 0\nvertex 1 0 0\nendloop\nendfacet\nendsolid t\n'; } > "$seeds/mesh_loader_fuzzer/tri.stl"
# Frames files: the shapes the README documents.
printf '{"frames": [{"weights": [0.5, 0.5]}]}' > "$seeds/frames_file_fuzzer/one.json"
printf '{"colliders": ["sphere:0,0,0,1"], "frames": [{"weights": [1, 0], "colliders": [{"translation": [0, 1, 0], "rotation": [1, 0, 0, 0]}], "pins": [{"vertex": 3, "position": [0, 0, 1]}]}]}' > "$seeds/frames_file_fuzzer/full.json"
# Takes: the edge take (lost rows, a weight above 1, rotations) and the first rows of the captured excerpt.
cp tests/data/take/edge_take.csv "$seeds/take_file_fuzzer/edge.csv"
head -n 4 tests/data/take/alex_rom_4_excerpt.csv > "$seeds/take_file_fuzzer/excerpt.csv"
# Upload chunks and solve requests: serialized protos written by the seed tool built with the targets.
"$out/fuzz/make_fuzz_seeds" "$seeds/upload_assembler_fuzzer" "$seeds/solve_request_fuzzer" "$seeds/cache_file_fuzzer" \
  tests/data/cylinder/cylinder.obj

# Each target runs in its own process, FUZZ_JOBS (default: the machine's cores) at a time; the reports follow in
# the targets' order once all have run.
run_target() {
  local t="$1"
  local corpus="$out/corpus/$t"
  mkdir -p "$corpus"
  local max_len=65536
  if [ "$t" = mesh_loader_fuzzer ]; then max_len=8192; fi
  local rc=0
  "$out/fuzz/$t" -max_total_time="$seconds" -max_len="$max_len" -rss_limit_mb=2048 -timeout=20 -print_final_stats=1 \
    -artifact_prefix="$out/findings/$t-" "$corpus" "$seeds/$t" > "$out/$t.log" 2>&1 || rc=$?
  echo "$rc" > "$out/$t.status"
}
jobs_at_once="${FUZZ_JOBS:-$(nproc)}"
for t in "${targets[@]}"; do
  while [ "$(jobs -rp | wc -l)" -ge "$jobs_at_once" ]; do wait -n || true; done
  echo "fuzz: $t for ${seconds} s"
  rm -f "$out/$t.status"
  run_target "$t" &
done
wait
status=0
for t in "${targets[@]}"; do
  log="$out/$t.log"
  corpus="$out/corpus/$t"
  if [ "$(cat "$out/$t.status" 2>/dev/null)" != 0 ]; then
    echo "fuzz: $t FOUND A PROBLEM; see $log and $out/findings/"
    grep -E "ERROR|SUMMARY|runtime error|uncaught|Test unit written" "$log" | head -20
    status=1
  fi
  execs=$(grep -E "stat::number_of_executed_units" "$log" | awk '{print $2}')
  cov=$(grep -E "^#[0-9]+.*(DONE|INITED)" "$log" | tail -1 | sed -E 's/.*cov: ([0-9]+).*/\1/')
  echo "fuzz: $t: ${execs:-?} executions, coverage ${cov:-?} edges, corpus $(ls "$corpus" | wc -l) inputs"
  grep -E "executions by format" "$log" | tail -1 | sed "s/^/fuzz: /" || true
done
exit $status
