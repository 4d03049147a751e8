#!/usr/bin/env bash
# A perf profile of the solve (not the rig build): runs `springblend-bench --profile` (the first method's sweep
# only) on one row, attaches `perf record` once the rig is built, and writes OUT/profile.md: the samples of the
# process grouped by where they fall (the 3n factorization: CHOLMOD's numeric factorization and the dense BLAS
# kernels it calls; the triangular solves with the factor; the spring passes; the Hessian products of the
# conjugate gradients; threading and the kernel; the rest), and the top symbols (every symbol in OUT/symbols.txt).
# Skips cleanly (exit 0, a line in profile.md) when perf is missing or not permitted, or the row's meshes are absent.
#   bash bench/profile.sh BUILD_DIR OUT_DIR [ROW [STEPS [METHOD [SHARED]]]]
#   (default: face 12 newton, and springblend-bench's own default for the shared meshes)
set -euo pipefail
build="${1:?build dir}"
out="${2:?output dir}"
row="${3:-face}"
steps="${4:-12}"
method="${5:-newton}"
shared_args=()
[ -n "${6:-}" ] && shared_args=(--shared "$6")
mkdir -p "$out"
report="$out/profile.md"
skip() {
  echo "profile skipped: $1" | tee "$report"
  exit 0
}
command -v perf > /dev/null || skip "perf is not installed (Debian: linux-perf)"
perf record -q -o /dev/null -- true > /dev/null 2>&1 || skip "perf record is not permitted here (perf_event_paranoid)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
log="$work/bench.log"
"$build/bench/springblend-bench" --rows "$row" --steps "$steps" --method "$method" "${shared_args[@]}" --profile --out "$work/out" \
  > /dev/null 2> "$log" &
bench=$!
# Wait for the rig (the build is not what is profiled), then record until the sweep ends.
until grep -q "rig built" "$log" 2> /dev/null; do
  if ! kill -0 "$bench" 2> /dev/null; then
    wait "$bench" || true
    grep -q "skipped" "$work/out/bench.md" 2> /dev/null && skip "row $row: $(grep -o 'skipped: [^|]*' "$work/out/bench.md" | head -1)"
    skip "springblend-bench ended before the rig was built: $(tail -1 "$log")"
  fi
  sleep 0.2
done
perf record -F 499 -o "$work/perf.data" -p "$bench" > /dev/null 2>&1 &
recorder=$!
wait "$bench"
wait "$recorder" || true
perf report -i "$work/perf.data" --no-children --sort dso,symbol --stdio --percent-limit 0 2> /dev/null |
  grep -E '^ +[0-9.]+%' > "$work/symbols.txt" || true
[ -s "$work/symbols.txt" ] || skip "perf recorded no samples"
cp "$work/symbols.txt" "$out/symbols.txt"
# Group the self samples. BLAS level-3 kernels and copies run inside CHOLMOD's supernodal factorization; the
# level-2 ones (trsv, gemv) inside its triangular solves with one right-hand side; Precondition is our own
# triangular solve with the factor rounded to single precision (the conjugate gradients' preconditioner).
python3 - "$work/symbols.txt" "$report" "$row" "$steps" "$method" "$(grep -c 'sweep frame' "$log")" << 'EOF'
import re, sys
symbols, report, row, steps, method, frames = sys.argv[1:]
groups = {}
order = ["3n factorization (numeric, BLAS level 3)", "triangular solves with the factor",
         "spring passes (forces, energy, Hessian blocks)", "Hessian products (conjugate gradients)",
         "vector work and allocation (Eigen, memset, memcpy)", "threading (TBB, OpenMP, kernel scheduling)",
         "other"]
top = []
for line in open(symbols):
    m = re.match(r"\s*([0-9.]+)%\s+(\S+)\s+\[(.)\]\s+(.*?)\s*(?:-\s+-\s*)?$", line)
    if not m:
        continue
    pct, dso, _, sym = float(m.group(1)), m.group(2), m.group(3), m.group(4)
    s = sym
    s = s.replace("(anonymous namespace)::", "")
    if "HessianProduct" in s:
        g = order[3]
    elif "TreeCholesky::" in s:
        # our two-thread numeric factorization (tree_cholesky.cc): assembly and scattering its updates
        g = order[0]
    elif "Cholesky::Precondition" in s or re.search(
            r"RoundedSupernodalSolve|Solve(Avx512|Avx2|Generic)\b|(Avx512|Avx2|Generic)(Forward|Backward)", s):
        # our supernodal solve with the factor rounded to single precision (rounded_solve.cc's kernels)
        g = order[1]
    elif "SpringSystem::Run" in s or "SpringSystem::Energy" in s:
        g = order[2]
    elif "openblas" in dso or "libblas" in dso or "liblapack" in dso:
        g = order[1] if re.search(r"trsv|gemv", s) else order[0]
    elif "cholmod" in dso:
        g = order[1] if re.search(r"solve", s) else order[0]
    elif re.search(r"tbb|gomp|sched_yield|futex|pthread", dso + s) or dso.startswith("[kernel"):
        g = order[5]
    elif re.search(r"memset|memcpy|memmove|Eigen|malloc|free", s):
        g = order[4]
    else:
        g = order[6]
    groups[g] = groups.get(g, 0.0) + pct
    short = re.sub(r"\(.*", "", s)[:90]
    top.append((pct, dso, short))
with open(report, "w") as f:
    f.write(f"# perf profile: {row}, {method}, sweep of {steps} frames ({frames} solved), rig build excluded\n\n")
    f.write("`perf record -F 499 -p <springblend-bench>` attached after the rig build; self samples grouped by "
            "where they fall (bench/profile.sh).\n\n| where | share of samples |\n|---|---|\n")
    for g in order:
        f.write(f"| {g} | {groups.get(g, 0.0):.1f} % |\n")
    f.write("\nTop symbols (self):\n\n| % | object | symbol |\n|---|---|---|\n")
    for pct, dso, short in sorted(top, reverse=True)[:15]:
        f.write(f"| {pct:.2f} | {dso} | `{short}` |\n")
EOF
cat "$report"
