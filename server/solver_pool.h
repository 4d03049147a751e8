// A fixed set of solver threads with a bounded queue: work is refused (not queued without end) when the
// queue is full, so an overloaded server answers RESOURCE_EXHAUSTED at once instead of timing everyone out.
#pragma once

#include <chrono>
#include <condition_variable>
#include <deque>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

namespace springblend::server {

class SolverPool {
 public:
  // `waited` (optional) is told, on the worker, how long each job waited in the queue, in seconds.
  SolverPool(int threads, int queue_capacity, std::function<void(double)> waited = {});
  ~SolverPool();  // finishes queued and running jobs, then joins
  SolverPool(const SolverPool&) = delete;
  SolverPool& operator=(const SolverPool&) = delete;

  // False when the queue is full or the pool is stopping. `interactive` as for SubmitContinuation.
  bool TrySubmit(std::function<void()> job, bool interactive = false);
  // The next step of work already admitted (a stream's next frame once the previous one is sent): queued
  // even when the queue is full, since refusing it would drop a stream half done. False only when stopping.
  // An `interactive` job (a slider session's) runs before every queued job that is not: a bake's many frames
  // never stand between an artist and the next answer.
  bool SubmitContinuation(std::function<void()> job, bool interactive = false);
  int queue_depth() const;
  int busy() const;
  int threads() const { return static_cast<int>(workers_.size()); }

 private:
  struct Job {
    std::function<void()> run;
    std::chrono::steady_clock::time_point queued;
  };
  void Run();

  const size_t capacity_;
  const std::function<void(double)> waited_;
  mutable std::mutex mutex_;
  std::condition_variable wake_;
  std::deque<Job> queue_;        // in submission order
  std::deque<Job> interactive_;  // before queue_
  int busy_ = 0;
  bool stopping_ = false;
  std::vector<std::thread> workers_;
};

}  // namespace springblend::server
