#include "watchdog.h"

#include "status.h"

namespace springblend::server {

std::int64_t Watchdog::Handle::Now() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

void Watchdog::Handle::Done() {
  std::lock_guard lock(mutex_);
  done_ = true;
}

const char* Watchdog::Handle::Overdue(std::int64_t now, const StreamTimeouts& timeouts) const {
  const std::int64_t waiting = waiting_since_.load(std::memory_order_relaxed);
  if (waiting != 0 && timeouts.stall.count() > 0 && now - waiting > std::chrono::nanoseconds(timeouts.stall).count()) {
    return "the stream stalled: the client neither read nor sent for longer than --stall-seconds";
  }
  if (idle_.count() > 0 && busy_.load(std::memory_order_relaxed) == 0 &&
      now - last_activity_.load(std::memory_order_relaxed) > std::chrono::nanoseconds(idle_).count()) {
    return "the Interactive session was idle for longer than --idle-seconds";
  }
  return nullptr;
}

Watchdog::Watchdog(StreamTimeouts timeouts) : timeouts_(timeouts), thread_([this] { Run(); }) {}

Watchdog::~Watchdog() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  thread_.join();
}

std::shared_ptr<Watchdog::Handle> Watchdog::Watch(grpc::ServerContextBase* call, bool idle) {
  auto handle = std::make_shared<Handle>();
  handle->call_ = call;
  handle->idle_ = idle ? timeouts_.idle : std::chrono::milliseconds(0);
  std::lock_guard lock(mutex_);
  handles_.push_back(handle);
  return handle;
}

void Watchdog::Run() {
  const auto period = std::clamp(std::min(timeouts_.stall, timeouts_.idle) / 4, std::chrono::milliseconds(20),
                                 std::chrono::milliseconds(500));
  std::unique_lock lock(mutex_);
  while (!wake_.wait_for(lock, period, [this] { return stopping_; })) {
    std::vector<std::shared_ptr<Handle>> handles = handles_;
    lock.unlock();
    const std::int64_t now = Handle::Now();
    for (const auto& h : handles) {
      const char* why = h->Overdue(now, timeouts_);
      if (why == nullptr || h->expired_.load() != nullptr) continue;
      std::lock_guard call_lock(h->mutex_);
      if (h->done_) continue;
      h->expired_.store(why);
      CancelCall(h->call_, Cancelled(why));
    }
    lock.lock();
    std::erase_if(handles_, [](const std::shared_ptr<Handle>& h) {
      std::lock_guard call_lock(h->mutex_);
      return h->done_;
    });
  }
}

}  // namespace springblend::server
