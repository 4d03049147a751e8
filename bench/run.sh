#!/usr/bin/env bash
# The benchmark in one command: installs the dependencies (Debian 12), builds the bench configuration, runs
# springblend-bench (every row whose meshes are present; per row the three solve methods side by side and the
# direct-Newton baseline on the same frames), a perf profile of the face's solve (bench/profile.sh), the slider
# drag through a server (bench/slider.py), the service throughput script and the sparse backends' comparison
# (bench/linear_algebra.sh), and writes bench-results/{bench.md,bench.json,ms_per_step.png,paths.md,paths.json,
# face-52/paths.md,face-52/paths.json,bake.md,bake.json,profile.md,slider.md,slider.json,service.md,
# linear_algebra.md}.
#   bash bench/run.sh [springblend-bench options, e.g. --rows face,horse --steps 36 --shared DIR]
# Without --steps (or --quick) the sweep has 18 frames (17 solved per pass), so that the whole run, every row
# with all three methods, the baseline and the reference, took 37 minutes on two cores before the three
# random-mix rows, which add about 25 more (estimated from horse-random's quick run: its rig 226 s, frames 1-6 s),
# and the paths bench's face-52 row about ten more.
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/install-deps.sh
cmake -S . -B build/bench -G Ninja -DCMAKE_BUILD_TYPE=Release -DSPRINGBLEND_BUILD_BENCH=ON \
  -DSPRINGBLEND_BUILD_TESTS=OFF > /dev/null
cmake --build build/bench --target springblend-bench springblend-paths-bench springblend-bake-bench \
  springblend-take-bench springblend \
  springblend-server springblend-tetgen springblend_python -j "$(nproc)"
# The profile and the slider drag read the shared meshes from the same place as springblend-bench.
shared="$(cd .. && pwd)/shared/meshes"
defaults=(--steps 18)
args=("$@")
for ((i = 0; i < ${#args[@]}; i++)); do
  case "${args[i]}" in
    --shared) shared="${args[i + 1]:-$shared}" ;;
    --shared=*) shared="${args[i]#--shared=}" ;;
    --steps | --steps=* | --quick) defaults=() ;;
  esac
done
status=0
build/bench/bench/springblend-bench --out bench-results "${defaults[@]}" "$@" || status=$?
# The target paths: build time and samples per target, path frames (17 off-sample alphas per target) against the
# full solve from the same start and a 1e-12 reference, memory, and a restart from the saved paths.
build/bench/bench/springblend-paths-bench --out bench-results --shared "$shared" || status=$?
# A production face's count of expressions: 52 (the ICT face's 16 and 36 pairs of them), built as the server builds
# an upload (each path spooled as it is solved): the build's peak, the rig's resident memory, built and restarted.
# About ten minutes.
build/bench/bench/springblend-paths-bench --rows face-52 --frames 5 --targets 1 --no-reference --spool \
  --out bench-results/face-52 --shared "$shared" || status=$?
# A face driven by a captured take: the shared face's 55 expressions uploaded as a user would (the build's time
# reported; about 4 minutes on two cores, its paths kept in bench-results/take for reruns), 120 consecutive frames
# of the shared Live Link Face take solved with the default (superposed) mix, and every sixth of them with the
# paper's blend of rest lengths (seconds a frame): ms, Newton iterations, pops, distance from the linear blend,
# certified minima; the worst frame of each as OBJ beside its linear blend.
build/bench/bench/springblend-take-bench --out bench-results/take --cache bench-results/take/face55.paths \
  --first 1500 --count 120 --models superposed || status=$?
build/bench/bench/springblend-take-bench --out bench-results/take-paper --cache bench-results/take/face55.paths \
  --first 1500 --count 20 --stride 6 --models superposed,rest-lengths || status=$?
# Baked plain rigs (bake-rig) against solved frames: single targets at held-out weights, pairs, five-target mixes.
build/bench/bench/springblend-bake-bench --out bench-results --shared "$shared" || status=$?
bash bench/profile.sh build/bench bench-results face 12 newton "$shared" || status=$?
/usr/bin/python3 bench/slider.py --build build/bench --out bench-results --shared "$shared" || status=$?
bash bench/service.sh build/bench bench-results
# The sparse Cholesky backends (CHOLMOD, MUMPS single precision) on one frame per row.
bash bench/linear_algebra.sh build/bench bench-results "$shared" || status=$?
exit "$status"
