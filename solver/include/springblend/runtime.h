// Process-wide settings for the numerical libraries, applied once at program start.
#pragma once

namespace springblend {

// CHOLMOD (SuiteSparse 5) opens OpenMP regions with a fixed four threads inside every supernodal
// factorization, and OpenBLAS starts a thread per core; on a small machine that already runs one solve per
// core, those threads only fight (measured: 2x slower factorizations, mostly in sched_yield). libgomp reads
// its limits from the environment when it loads, before main runs, so this sets OMP_THREAD_LIMIT=1 and
// OPENBLAS_NUM_THREADS=1 (unless the caller set them) and re-executes the program once. Parallelism comes
// from springblend's own threads instead. Call it first thing in main; it returns normally when nothing
// needs doing or the re-exec is impossible.
void ConfigureNumericalThreads(char** argv);

}  // namespace springblend
