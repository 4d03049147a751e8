// Running TetGen in a helper process. TetGen 1.5 ends a failed run by throwing an int (or, built without
// TETLIBRARY, by exit()), can crash or loop forever on bad input, and prints to stdout, so it never runs in the
// caller's process: springblend-tetgen (tetgen_helper.cc), a small executable of ours, runs it and sends the
// result back through a pipe as raw arrays. This file is the parent's side: find the helper, write the request
// into an in-memory file, spawn, read the result under a deadline, reap. What the result means is
// tetrahedralize.cc's business.
//
// The helper is started with posix_spawn (a fork of a multithreaded process may only call async-signal-safe
// functions until it execs; spawning a fresh image avoids the question). It dies with its parent
// (PR_SET_PDEATHSIG, which follows the spawning thread: the calling thread waits for the helper before it
// returns, so that is the same thing here) and has its own CPU limit (RLIMIT_CPU, from the timeout).
#pragma once

#include <sys/types.h>

#include <chrono>
#include <optional>
#include <string>
#include <vector>

#include "springblend/geometry.h"
#include "tetgen_protocol.h"

namespace springblend::internal::tetgen {

using Clock = std::chrono::steady_clock;

// The helper executable: the path given to SetTetGenHelper (springblend/runtime.h), else the
// SPRINGBLEND_TETGEN_HELPER environment variable, else the first of springblend-tetgen next to the running
// program, in ../libexec/springblend relative to it, in the installed libexec directory. Throws Error(kInternal) naming
// the places it looked when none is an executable file (a broken installation, not a bad surface).
std::string FindHelper();

struct Outcome {
  bool timed_out = false;
  bool complete = false;  // a whole message arrived
  MessageHeader header{};
  std::vector<char> payload;
  std::optional<int> wait_status;  // empty if it could not be collected
};

// One started helper: however the parent leaves, the pipe is closed and the helper killed and reaped.
class HelperProcess {
 public:
  // Writes the request and spawns the helper; throws Error(kNumerical) when it cannot be started.
  // cpu_seconds <= 0: no CPU limit.
  HelperProcess(const Points& vertices, const Faces& faces, const std::string& switches, Task task,
                std::int64_t cpu_seconds);
  HelperProcess(const HelperProcess&) = delete;
  HelperProcess& operator=(const HelperProcess&) = delete;
  ~HelperProcess();

  pid_t pid() const { return pid_; }

  // Reads the helper's message until it is complete, the helper ends, or `deadline` (then it is killed), and
  // reaps it. Call once.
  Outcome Collect(Clock::time_point deadline);

 private:
  std::optional<int> Reap(bool kill_first);

  pid_t pid_ = -1;
  int fd_ = -1;  // the read end of the result pipe
};

// The CPU limit for a helper that has `timeout_seconds` of wall time: a little more, so that the deadline
// normally comes first; 0 (none) for timeouts too long to matter.
std::int64_t CpuSecondsFor(double timeout_seconds);

}  // namespace springblend::internal::tetgen
