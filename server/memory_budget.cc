#include "memory_budget.h"

#include <fmt/format.h>

#include "status.h"

namespace springblend::server {

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

void Reservation::Grow(std::int64_t bytes) {
  if (bytes <= 0 || budget_ == nullptr) return;
  if (!budget_->TryReserve(bytes)) {
    throw LimitError(fmt::format("the server's memory for uploads in progress and open streams is in use ({} of {} MiB, "
                                 "--request-memory-mb); retry later or add replicas",
                                 budget_->used() >> 20, budget_->limit() >> 20));
  }
  bytes_ += bytes;
}

}  // namespace springblend::server
