#!/usr/bin/env bash
# The sparse Cholesky backends side by side in one run: one frame per row solved alone from the linear blend
# (no target paths, so every Newton step factors or solves with the backend), at weight 0.55, with CHOLMOD
# (the default: double factor, preconditioning with it rounded to single precision), CHOLMOD preconditioning
# with the double factor (cholmod-double) and MUMPS (single precision). Per row and backend: factorizations, factorize ms, solve
# ms (the triangular solves and conjugate gradients), Newton iterations, energy and wall time, as markdown.
# Rows: the bundled ICT face (jawOpen) always; the horse and the cat when the shared meshes are present.
#   bash bench/linear_algebra.sh [BUILD_DIR (default build/bench)] [OUT_DIR (default bench-results)] [SHARED]
# Environment: WEIGHT (default 0.55), BACKENDS (default "cholmod cholmod-double mumps").
set -euo pipefail
cd "$(dirname "$0")/.."
build="${1:-build/bench}"
out="${2:-bench-results}"
shared="${3:-$(cd .. && pwd)/shared/meshes}"
weight="${WEIGHT:-0.55}"
backends="${BACKENDS:-cholmod cholmod-double mumps}"
cli="$build/client/springblend"
[ -x "$cli" ] || { echo "linear_algebra.sh: $cli is missing; build the bench preset first (see README, Benchmark)" >&2; exit 2; }
mkdir -p "$out"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

rows=("face tests/data/face/generic_neutral_mesh.obj tests/data/face/jawOpen.obj")
if [ -f "$shared/horse/horse-01.obj" ]; then rows+=("horse $shared/horse/horse-reference.obj $shared/horse/horse-01.obj"); fi
if [ -f "$shared/cat/cat-01.obj" ]; then rows+=("cat $shared/cat/cat-reference.obj $shared/cat/cat-01.obj"); fi

for row in "${rows[@]}"; do
  read -r name rest target <<< "$row"
  for backend in $backends; do
    start=$(date +%s.%N)
    "$cli" blend --rest "$rest" --target "$target" --weights "$weight" --no-target-paths --solver "$backend" \
      --out "$work/$name-$backend.obj" > "$work/$name-$backend.jsonl"
    end=$(date +%s.%N)
    echo "$name $backend $start $end" >> "$work/runs.txt"
  done
done

/usr/bin/python3 - "$work" "$weight" > "$out/linear_algebra.md" <<'EOF'
import json, sys
work, weight = sys.argv[1], sys.argv[2]
print(f"# Sparse Cholesky backends\n\nOne frame alone at weight {weight}, no target paths "
      "(`springblend blend --no-target-paths --solver BACKEND`); wall includes loading and the rig build.\n")
print("| row | backend | factorizations | factorize ms | solve ms | Newton iterations | energy | wall s |")
print("|---|---|---:|---:|---:|---:|---:|---:|")
for line in open(f"{work}/runs.txt"):
    name, backend, start, end = line.split()
    frame = json.loads(open(f"{work}/{name}-{backend}.jsonl").read().strip().splitlines()[-1])
    print(f"| {name} | {backend} | {frame['factorizations']} | {frame['factorize_ms']:.0f} | {frame['solve_ms']:.0f} "
          f"| {frame['newton_iterations']} | {frame['energy']:.9g} | {float(end) - float(start):.2f} |")
EOF
cat "$out/linear_algebra.md"
