#include "watchdog.h"

namespace springblend::server {

std::int64_t Watchdog::Handle::Now() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

void Watchdog::Handle::Done() {
  std::lock_guard lock(mutex_);
  done_ = true;
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
      const std::int64_t waiting = h->waiting_since_.load(std::memory_order_relaxed);
      const char* why = nullptr;
      if (waiting != 0 && timeouts_.stall.count() > 0 &&
          now - waiting > std::chrono::nanoseconds(timeouts_.stall).count()) {
        why = "the stream stalled: the client neither read nor sent for longer than --stall-seconds";
      } else if (h->idle_.count() > 0 &&
                 now - h->last_activity_.load(std::memory_order_relaxed) > std::chrono::nanoseconds(h->idle_).count()) {
        why = "the Interactive session was idle for longer than --idle-seconds";
      }
      if (why == nullptr || h->expired_.load() != nullptr) continue;
      std::lock_guard call_lock(h->mutex_);
      if (h->done_) continue;
      h->expired_.store(why);
      h->call_->TryCancel();
    }
    lock.lock();
    std::erase_if(handles_, [](const std::shared_ptr<Handle>& h) {
      std::lock_guard call_lock(h->mutex_);
      return h->done_;
    });
  }
}

}  // namespace springblend::server
