#include "memory_budget.h"

#include <fmt/format.h>

#include <algorithm>

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
