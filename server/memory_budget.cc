#include "memory_budget.h"

#include <fmt/format.h>
#include <malloc.h>

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <thread>

#include "status.h"

namespace springblend::server {
namespace {

// One thread that trims the heap when asked: 200 ms after the last ask (the calls' buffers are freed when they end,
// just after their answer), and at most 1 s after the first of a run of asks.
class HeapTrimmer {
 public:
  void Ask() {
    const auto now = std::chrono::steady_clock::now();
    {
      std::lock_guard lock(mutex_);
      if (!pending_) first_ = now;
      pending_ = true;
      due_ = std::min(now + std::chrono::milliseconds(200), first_ + std::chrono::seconds(1));
    }
    wake_.notify_one();
  }
  void Run() {
    std::unique_lock lock(mutex_);
    for (;;) {
      wake_.wait(lock, [this] { return pending_; });
      while (std::chrono::steady_clock::now() < due_) wake_.wait_until(lock, due_);
      pending_ = false;
      lock.unlock();
#if defined(__GLIBC__)
      malloc_trim(0);
#endif
      lock.lock();
    }
  }

 private:
  std::mutex mutex_;
  std::condition_variable wake_;
  bool pending_ = false;
  std::chrono::steady_clock::time_point first_, due_;
};

}  // namespace

void ReturnFreeHeapSoon() {
  // Never destroyed: its thread runs for the process's life.
  static HeapTrimmer* const trimmer = [] {
    auto* t = new HeapTrimmer;
    std::thread([t] { t->Run(); }).detach();
    return t;
  }();
  trimmer->Ask();
}

bool MemoryBudget::TryReserve(std::int64_t bytes) {
  std::lock_guard lock(mutex_);
  if (bytes > limit_ - used_) return false;
  used_ += bytes;
  return true;
}

void MemoryBudget::Release(std::int64_t bytes) {
  std::lock_guard lock(mutex_);
  used_ -= bytes;
}

std::int64_t MemoryBudget::used() const {
  std::lock_guard lock(mutex_);
  return used_;
}

bool Reservation::TryGrow(std::int64_t bytes) {
  if (bytes <= 0 || budget_ == nullptr) return true;
  if (!budget_->TryReserve(bytes)) return false;
  bytes_ += bytes;
  return true;
}

void Reservation::Grow(std::int64_t bytes) {
  if (TryGrow(bytes)) return;
  const std::int64_t used = budget_->used();
  throw LimitError(fmt::format("this request needs {} bytes ({:.1f} MiB) more of the server's memory for requests in "
                               "progress, and {} bytes are free ({:.1f} of {} MiB in use, --request-memory-mb); "
                               "retry later, send fewer frames per request, or add replicas",
                               bytes, bytes / 1048576.0, std::max<std::int64_t>(0, budget_->limit() - used),
                               used / 1048576.0, budget_->limit() >> 20));
}

void Reservation::Shrink(std::int64_t bytes) {
  if (budget_ == nullptr || bytes <= 0) return;
  std::int64_t held = bytes_.load();
  while (!bytes_.compare_exchange_weak(held, held - std::min(held, bytes))) {
  }
  budget_->Release(std::min(held, bytes));
}

}  // namespace springblend::server
