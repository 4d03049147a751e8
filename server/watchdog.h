// Cancels calls that wait on their client too long, so no stream holds server memory (or, before, a worker) for
// ever: a stalled stream (a write the client does not read, or an upload whose next piece does not come) after
// the stall timeout, and an Interactive session with no new message after the idle timeout. One thread checks
// every watched call a few times a second; it cancels with CANCELLED and its reason as the message (which the
// client sees), after which the call's reactor finishes as on any cancellation.
#pragma once

#include <atomic>
#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include <grpcpp/server_context.h>

namespace springblend::server {

struct StreamTimeouts {
  std::chrono::milliseconds stall{std::chrono::seconds(60)};  // --stall-seconds
  std::chrono::milliseconds idle{std::chrono::seconds(600)};  // --idle-seconds (Interactive)
};

class Watchdog {
 public:
  // Shared by a call's reactor and the watchdog. The reactor says when it starts and stops waiting on its
  // client, and calls Done in OnDone; after that the watchdog never touches the call.
  class Handle {
   public:
    // A write handed to gRPC (or a read of an upload's next piece) that the client must complete.
    void Waiting() { waiting_since_.store(Now(), std::memory_order_relaxed); }
    // That write (or read) completed.
    void Progress() {
      waiting_since_.store(0, std::memory_order_relaxed);
      Activity();
    }
    // A message from the client that nothing waited for (an Interactive frame): resets only the idle clock.
    void Activity() { last_activity_.store(Now(), std::memory_order_relaxed); }
    // The server works for the call (a session's setup, solve or preview): a session waiting for its answer is
    // not idle, however long the work takes. The idle clock starts again when the last such work ends.
    void Busy() { busy_.fetch_add(1, std::memory_order_relaxed); }
    void Unbusy() {
      Activity();
      busy_.fetch_sub(1, std::memory_order_relaxed);
    }
    // Why the watchdog would cancel the call at `now` (Now()'s clock, nanoseconds), or nullptr.
    const char* Overdue(std::int64_t now, const StreamTimeouts& timeouts) const;
    void Done();
    // Why the watchdog cancelled the call (nullptr if it did not): for the status the reactor finishes with.
    const char* expired() const { return expired_.load(); }

   private:
    friend class Watchdog;

   public:
    static std::int64_t Now();

   private:
    std::recursive_mutex mutex_;  // recursive: TryCancel may run the reactor's OnDone inline on this thread
    grpc::ServerContextBase* call_ = nullptr;
    bool done_ = false;
    std::chrono::milliseconds idle_{0};
    std::atomic<std::int64_t> waiting_since_{0};
    std::atomic<std::int64_t> last_activity_{Now()};
    std::atomic<int> busy_{0};
    std::atomic<const char*> expired_{nullptr};
  };

  explicit Watchdog(StreamTimeouts timeouts);
  ~Watchdog();
  Watchdog(const Watchdog&) = delete;
  Watchdog& operator=(const Watchdog&) = delete;

  // idle: whether the idle timeout applies (Interactive sessions).
  std::shared_ptr<Handle> Watch(grpc::ServerContextBase* call, bool idle);
  const StreamTimeouts& timeouts() const { return timeouts_; }

 private:
  void Run();

  const StreamTimeouts timeouts_;
  std::mutex mutex_;
  std::condition_variable wake_;
  bool stopping_ = false;
  std::vector<std::shared_ptr<Handle>> handles_;
  std::thread thread_;
};

}  // namespace springblend::server
