#include "solver_pool.h"

namespace springblend::server {

SolverPool::SolverPool(int threads, int queue_capacity, std::function<void(double)> waited)
    : capacity_(static_cast<size_t>(queue_capacity)), waited_(std::move(waited)) {
  for (int i = 0; i < threads; ++i) workers_.emplace_back([this] { Run(); });
}

SolverPool::~SolverPool() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  for (auto& w : workers_) w.join();
}

bool SolverPool::TrySubmit(std::function<void()> job, bool interactive) {
  {
    std::lock_guard lock(mutex_);
    if (stopping_ || queue_.size() + interactive_.size() >= capacity_) return false;
    (interactive ? interactive_ : queue_).push_back({std::move(job), std::chrono::steady_clock::now()});
  }
  wake_.notify_one();
  return true;
}

bool SolverPool::SubmitContinuation(std::function<void()> job, bool interactive) {
  {
    std::lock_guard lock(mutex_);
    if (stopping_) return false;
    (interactive ? interactive_ : queue_).push_back({std::move(job), std::chrono::steady_clock::now()});
  }
  wake_.notify_one();
  return true;
}

int SolverPool::queue_depth() const {
  std::lock_guard lock(mutex_);
  return static_cast<int>(queue_.size() + interactive_.size());
}

int SolverPool::busy() const {
  std::lock_guard lock(mutex_);
  return busy_;
}

void SolverPool::Run() {
  for (;;) {
    Job job;
    {
      std::unique_lock lock(mutex_);
      wake_.wait(lock, [this] { return stopping_ || !queue_.empty() || !interactive_.empty(); });
      auto& from = !interactive_.empty() ? interactive_ : queue_;
      if (from.empty()) return;  // stopping and drained
      job = std::move(from.front());
      from.pop_front();
      ++busy_;
    }
    if (waited_) waited_(std::chrono::duration<double>(std::chrono::steady_clock::now() - job.queued).count());
    job.run();
    std::lock_guard lock(mutex_);
    --busy_;
  }
}

}  // namespace springblend::server
