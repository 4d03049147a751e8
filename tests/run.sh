#!/usr/bin/env bash
# Builds springblend and runs every test. Installs its own dependencies (Debian 12), works from a fresh clone.
#   bash tests/run.sh                       release build + all tests
#   PRESET=asan-ubsan bash tests/run.sh     the same under AddressSanitizer + UndefinedBehaviorSanitizer
#   PRESET=tsan TESTS='Server|Thread' TARGETS='integration_server_test ...' bash tests/run.sh
#                                           only the tests matching a regex (ctest -R), building only TARGETS
#   CMAKE_ARGS='-DSPRINGBLEND_BUILD_CLI=OFF' ...
#                                           extra configure arguments (kept in the build directory's cache)
#   EXCLUDE_LABELS='slow|install' ...       leave out tests with these CTest labels (ctest -LE), or, with
#   EXCLUDE_TESTS=REGEX, these tests (ctest -E); the sanitizer stages of .ci/run leave the long real-mesh
#                                           cases to the release stage
# Sanitizers stop a process at their first report (a server too, so its client's test fails); the options
# below keep that explicit. TSan's suppressions (tests/tsan.supp) say why each is there.
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/install-deps.sh
preset="${PRESET:-release}"
export ASAN_OPTIONS="${ASAN_OPTIONS:-detect_leaks=1:abort_on_error=0:halt_on_error=1}"
export UBSAN_OPTIONS="${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1}"
export TSAN_OPTIONS="${TSAN_OPTIONS:-halt_on_error=1:second_deadlock_stack=1:suppressions=$PWD/tests/tsan.supp}"
read -r -a configure_args <<< "${CMAKE_ARGS:-}"
cmake --preset "$preset" "${configure_args[@]}"
targets=()
if [ -n "${TARGETS:-}" ]; then read -r -a names <<< "$TARGETS"; targets=(--target "${names[@]}"); fi
cmake --build --preset "$preset" -j "$(nproc)" "${targets[@]}"
filter=()
if [ -n "${TESTS:-}" ]; then filter=(-R "$TESTS"); fi
if [ -n "${EXCLUDE_LABELS:-}" ]; then filter+=(-LE "$EXCLUDE_LABELS"); fi
if [ -n "${EXCLUDE_TESTS:-}" ]; then filter+=(-E "$EXCLUDE_TESTS"); fi
runner=()
# TBB's work stealing synchronises inside libtbb, which is not instrumented, so under TSan every parallel loop
# would look racy. On one CPU TBB starts no workers and runs parallel loops inline; our own threads (the
# server's pool, gRPC's, the tests') still interleave, and TSan judges by happens-before, not by timing.
if [ "$preset" = tsan ]; then runner=(taskset -c 0); fi
"${runner[@]}" ctest --preset "$preset" -j "$(nproc)" "${filter[@]}"
