// One memory budget for what requests hold while they run: uploads in progress (the bytes received so far) and
// open Solve and Interactive streams (an estimate of their colliders and solver state). Built characters have
// their own budget in the store (--memory-budget-mb). A request that would go over is refused with
// RESOURCE_EXHAUSTED instead of the server growing until the kernel kills it.
#pragma once

#include <cstdint>
#include <mutex>

namespace springblend::server {

class MemoryBudget {
 public:
  explicit MemoryBudget(std::int64_t limit_bytes) : limit_(limit_bytes) {}
  bool TryReserve(std::int64_t bytes);
  void Release(std::int64_t bytes);
  std::int64_t used() const;
  std::int64_t limit() const { return limit_; }

 private:
  const std::int64_t limit_;
  mutable std::mutex mutex_;
  std::int64_t used_ = 0;
};

// What one request holds of the budget; released when it goes. Grow throws LimitError (RESOURCE_EXHAUSTED).
class Reservation {
 public:
  explicit Reservation(MemoryBudget* budget) : budget_(budget) {}  // null: nothing is counted
  ~Reservation() {
    if (budget_) budget_->Release(bytes_);
  }
  Reservation(const Reservation&) = delete;
  Reservation& operator=(const Reservation&) = delete;
  void Grow(std::int64_t bytes);
  std::int64_t bytes() const { return bytes_; }

 private:
  MemoryBudget* budget_;
  std::int64_t bytes_ = 0;
};

}  // namespace springblend::server
