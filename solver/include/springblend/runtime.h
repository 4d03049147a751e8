// Process-wide settings for the numerical libraries, applied once at program start.
#pragma once

#include <string>

namespace springblend {

// CHOLMOD (SuiteSparse 5) opens OpenMP regions with a fixed four threads inside every supernodal
// factorization, and OpenBLAS starts a thread per core; on a small machine that already runs one solve per
// core, those threads only fight (measured: 2x slower factorizations, mostly in sched_yield). libgomp reads
// its limits from the environment when it loads, before main runs, so this sets OMP_THREAD_LIMIT=1 and
// OPENBLAS_NUM_THREADS=1 (unless the caller set them) and re-executes the program once. Parallelism comes
// from springblend's own threads instead. Call it first thing in main; it returns normally when nothing
// needs doing or the re-exec is impossible.
void ConfigureNumericalThreads(char** argv);

// TetGen runs in a helper program of ours, springblend-tetgen, never in the caller's process. The solver runs
// the one at the path given here (empty: not set), else the one at $SPRINGBLEND_TETGEN_HELPER, else the first
// it finds next to the running program, in ../libexec/springblend relative to it (the installed layout) or in
// the installed libexec directory. A helper that is not there is an Error(kInternal) naming where it looked.
// A plug-in inside a host application (whose executable is not ours) calls this or sets the variable, or relies on
// the installed location. Safe to call at any time; the next tetrahedralization uses it.
void SetTetGenHelper(const std::string& path);

}  // namespace springblend
