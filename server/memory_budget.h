// One memory budget for what requests hold while they run: uploads in progress (the bytes received so far), Solve
// requests (their bytes as received, then parsed, and their converted frames until written) and open Solve and
// Interactive streams (their colliders and each Solver, counted from the factor size the rig's analysis knows,
// Solver::bytes). Built characters have
// their own budget in the store (--memory-budget-mb). A request that would go over is refused with
// RESOURCE_EXHAUSTED instead of the server growing until the kernel kills it.
#pragma once

#include <atomic>
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

// What one request holds of the budget; released when it goes. Grow throws LimitError (RESOURCE_EXHAUSTED,
// saying how many bytes were asked and how many are free). Safe to use from several threads.
class Reservation {
 public:
  explicit Reservation(MemoryBudget* budget) : budget_(budget) {}  // null: nothing is counted
  ~Reservation() {
    if (budget_) budget_->Release(bytes_.load());
  }
  Reservation(const Reservation&) = delete;
  Reservation& operator=(const Reservation&) = delete;
  void Grow(std::int64_t bytes);
  // Grow without throwing: false (and nothing reserved) when the budget has no room.
  bool TryGrow(std::int64_t bytes);
  // Gives back part of what was reserved (memory the request no longer holds), at most all of it.
  void Shrink(std::int64_t bytes);
  std::int64_t bytes() const { return bytes_.load(); }

 private:
  MemoryBudget* budget_;
  std::atomic<std::int64_t> bytes_{0};
};

// Gives the process's free heap back to the system (glibc's malloc_trim) a moment from now, on a thread of its
// own: a large request gRPC received whole (up to ServerOptions::max_receive_message_bytes, before any handler
// runs, even one refused for its token) is freed in pieces over several allocator arenas, which glibc otherwise
// keeps: eight unauthenticated 64 MiB requests left the server's resident set 330 MiB higher for good. Calls
// close together share one trim. Thread-safe; does nothing off glibc.
void ReturnFreeHeapSoon();
// A request message at least this large asks for it.
inline constexpr std::int64_t kLargeRequestBytes = 1 << 20;

}  // namespace springblend::server
