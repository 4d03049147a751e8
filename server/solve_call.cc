#include <fmt/format.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <map>
#include <memory>
#include <mutex>
#include <optional>

#include "call_support.h"
#include "calls.h"
#include "springblend/error.h"

namespace springblend::server {
namespace {

// A Solve stream. Frames are independent (stateless frames), so up to one per pool thread are solved at once,
// each on a worker of its own, and written in order as they become ready: one long bake uses every core. At
// most that many solved-or-solving frames exist at a time (a slow reader holds them, not more), and a worker
// returns to the pool as soon as its frame is stored; the next frames are queued as writes complete. The
// stream finishes only when no job of it is running any more. One that stops reading is cancelled by the
// watchdog (--stall-seconds). The memory budget counts the parsed request until it is converted, each converted
// frame until it is written, the colliders and the solvers (one per frame solved at once, as many as fit).
class SolveReactor final : public grpc::ServerWriteReactor<grpc::ByteBuffer> {
 public:
  // `received` holds the request's bytes as gRPC received them: given back once the parsed request is counted.
  SolveReactor(grpc::CallbackServerContext* call, ServiceContext& context, v1::SolveRequest request,
               Reservation& received)
      : call_(call),
        context_(context),
        request_(std::move(request)),
        watch_(context.watchdog.Watch(call, false)),
        memory_(&context.memory),
        solvers_charge_(context.metrics) {
    info_ = BeginCall(call, "Solve");
    info_.character = request_.character_id();
    info_.frames = request_.frames_size();
    std::unique_lock lock(mutex_);
    try {
      request_bytes_ = RequestBytes(request_);
      memory_.Grow(request_bytes_);
      received.Shrink(received.bytes());
    } catch (const std::exception& e) {
      Act(lock, Fail(ToStatus(e)));
      return;
    }
    running_ = 1;
    if (!context_.pool.TrySubmit([this] { Start(); })) {
      running_ = 0;
      Act(lock, Fail(kQueueFull));
    }
  }

  void OnWriteDone(bool ok) override {
    watch_->Progress();
    std::unique_lock lock(mutex_);
    writing_ = false;
    if (!ok) {
      Act(lock, Fail(StoppedStatus(*watch_, "the client cancelled the stream")));
      return;
    }
    // Written: the frame's converted input is not needed any more.
    Frame& done = job_.frames[written_++];
    memory_.Shrink(FrameBytes(done));
    done = Frame();
    const Action action = Schedule();
    Act(lock, action != Action::kNone ? action : WriteOrFinish());
  }
  void OnDone() override {
    watch_->Done();
    delete this;
  }

 private:
  // On a pool worker: the character found, or, while it is being built (an upload, or a rebuild from the cache
  // directory after a restart), the stream waits for the build within its deadline without holding the worker:
  // the build's end queues Begin.
  void Start() {
    CharacterStore::Found found;
    try {
      CheckId(request_.character_id(), "character_id");
      found = context_.store.Find(request_.character_id(), true, BuildWants(call_, context_));
    } catch (const std::exception& e) {
      Begin(nullptr, std::current_exception());
      return;
    }
    if (!found.building) {
      Begin(found.entry, nullptr);
      return;
    }
    waiter_ = std::move(found.waiter);
    found.building->OnDone([this](const std::shared_ptr<const CharacterStore::Entry>& entry, std::exception_ptr error) {
      if (!context_.pool.SubmitContinuation([this, entry, error] { Begin(entry, error); })) {
        Begin(nullptr, std::make_exception_ptr(std::runtime_error("the server is shutting down")));
      }
    });
  }

  // The request's conversion (its colliders once), then the first frames.
  void Begin(std::shared_ptr<const CharacterStore::Entry> entry, std::exception_ptr error) {
    waiter_.reset();
    try {
      if (error) std::rethrow_exception(error);
      entry_ = std::move(entry);
      if (!entry_) throw StatusError(NotFound(request_.character_id()));
      if (Expired()) throw StatusError(DeadlineExceeded("the deadline passed while the character was being built"));
      // The colliders and the converted frames, counted before they are made.
      std::int64_t frames = 0;
      for (const v1::FrameRequest& f : request_.frames()) frames += FrameBytes(f);
      memory_.Grow(StreamBytes(request_.colliders()) + frames);
      job_ = ToSolveJob(request_, *entry_->rig, context_.limits, [this] { return call_->IsCancelled() || Expired(); });
      // Converted: the parsed request is let go.
      v1::SolveRequest().Swap(&request_);
      memory_.Shrink(request_bytes_);
      colliders_ = std::move(job_.colliders);
      context_.metrics.CountColliders(colliders_.size());
      // One solver per frame solved at once: one is needed, the others as the budget has room.
      const int wanted = static_cast<int>(std::max<size_t>(1, std::min<size_t>(context_.pool.threads(), job_.frames.size())));
      in_flight_limit_ = static_cast<size_t>(
          solvers_charge_.Reserve(memory_, Solver::BytesFor(*entry_->rig, job_.options), 1, wanted));
    } catch (const StatusError& e) {
      std::unique_lock lock(mutex_);
      --running_;
      Act(lock, Fail(e.status));
      return;
    } catch (const std::exception& e) {
      std::unique_lock lock(mutex_);
      --running_;
      Act(lock, Fail(BuildStatus(e, call_, context_)));
      return;
    }
    std::unique_lock lock(mutex_);
    --running_;
    started_ = true;
    const Action action = Schedule();
    Act(lock, action != Action::kNone ? action : FinishIfDone());
  }

  enum class Action { kNone, kWrite, kFinish };
  // Done after the lock is released: gRPC may run OnWriteDone or OnDone (which deletes this) at once.
  void Act(std::unique_lock<std::mutex>& lock, Action action) {
    lock.unlock();
    if (action == Action::kWrite) {
      StartWrite(&frame_);
    } else if (action == Action::kFinish) {
      EndCall(context_.metrics, info_, final_status_);
      Finish(final_status_);
    }
  }

  // Under the lock: queues jobs for the next frames while fewer than in_flight_limit_ frames are solving or
  // waiting to be written. A refusal (the pool is stopping) fails the stream.
  Action Schedule() {
    while (started_ && !failed_ && next_ < job_.frames.size() &&
           static_cast<size_t>(running_) + ready_.size() < in_flight_limit_) {
      const size_t i = next_++;
      ++running_;
      if (!context_.pool.SubmitContinuation([this, i] { SolveFrame(i); })) {
        --running_;
        return Fail(kShuttingDown);
      }
    }
    return Action::kNone;
  }

  // On a pool worker.
  void SolveFrame(size_t i) {
    std::optional<grpc::Status> error;
    grpc::ByteBuffer bytes;
    if (call_->IsCancelled() || Expired()) {
      error = Expired() ? DeadlineExceeded(fmt::format("deadline passed after {} of {} frames", i, job_.frames.size()))
                        : StoppedStatus(*watch_, "the client cancelled the stream");
    } else {
      try {
        std::unique_ptr<Solver> solver = TakeSolver();
        Points positions;
        // A cancelled or expired stream stops its frames within a Newton iteration.
        const SolveSummary summary =
            solver->Solve(job_.frames[i], &positions, [this] { return call_->IsCancelled() || Expired(); });
        ReturnSolver(std::move(solver));
        if (summary.termination == Termination::kCancelled) {
          error = Expired() ? DeadlineExceeded(fmt::format("deadline passed during frame {} of {}", i,
                                                           job_.frames.size()))
                            : StoppedStatus(*watch_, "the client cancelled the stream");
        } else {
          context_.metrics.CountFrame(summary.solve_ms / 1000.0, summary.newton_iterations, summary.converged());
          CheckSolved(positions, i);
          bytes = Serialize(ToProto(static_cast<int>(i), positions, entry_->rig->rest().faces, summary,
                                    job_.with_normals, context_.replica_name));
        }
      } catch (const std::exception& e) {
        error = FrameStatus(e, entry_, context_);
      }
    }
    std::unique_lock lock(mutex_);
    --running_;
    if (error) {
      Act(lock, Fail(*error));
      return;
    }
    ready_.emplace(i, std::move(bytes));
    const Action action = Schedule();
    Act(lock, action != Action::kNone ? action : WriteOrFinish());
  }

  std::unique_ptr<Solver> TakeSolver() {
    {
      std::lock_guard lock(mutex_);
      if (!solvers_.empty()) {
        std::unique_ptr<Solver> solver = std::move(solvers_.back());
        solvers_.pop_back();
        return solver;
      }
    }
    auto solver = std::make_unique<Solver>(entry_->rig, job_.options);
    solver->SetColliders(colliders_);
    return solver;
  }
  void ReturnSolver(std::unique_ptr<Solver> solver) {
    std::lock_guard lock(mutex_);
    solvers_.push_back(std::move(solver));
  }

  // Under the lock: the next frame in order when it is ready and no write is in flight; else whether the stream
  // is done (every frame written, or failed, and nothing of it runs).
  Action WriteOrFinish() {
    if (!failed_ && !writing_) {
      const auto it = ready_.find(written_);
      if (it != ready_.end()) {
        frame_ = std::move(it->second);
        ready_.erase(it);
        writing_ = true;
        watch_->Waiting();
        return Action::kWrite;
      }
    }
    return FinishIfDone();
  }
  Action Fail(const grpc::Status& status) {
    if (!failed_) failed_ = status;
    ready_.clear();
    return FinishIfDone();
  }
  Action FinishIfDone() {
    if (finished_ || running_ > 0 || writing_) return Action::kNone;
    if (!failed_ && !(started_ && written_ == job_.frames.size())) return Action::kNone;
    finished_ = true;
    final_status_ = failed_ ? *failed_ : grpc::Status::OK;
    return Action::kFinish;
  }

  bool Expired() const { return std::chrono::system_clock::now() > call_->deadline(); }

  struct StatusError : std::exception {
    explicit StatusError(grpc::Status s) : status(std::move(s)) {}
    grpc::Status status;
  };

  grpc::CallbackServerContext* call_;
  ServiceContext& context_;
  CallInfo info_;
  OpenCall open_{context_.metrics.solve_streams};
  v1::SolveRequest request_;
  std::shared_ptr<Watchdog::Handle> watch_;
  Reservation memory_;
  SolverCharge solvers_charge_;
  std::int64_t request_bytes_ = 0;  // the parsed request, counted until converted
  std::shared_ptr<const CharacterStore::Entry> entry_;
  CharacterStore::Waiter waiter_;  // while the character is being built
  SolveJob job_;
  std::vector<Collider> colliders_;
  std::mutex mutex_;
  std::vector<std::unique_ptr<Solver>> solvers_;  // idle ones, reused by the next frames
  std::map<size_t, grpc::ByteBuffer> ready_;       // solved, waiting for their turn to be written
  size_t in_flight_limit_ = 1;
  size_t next_ = 0;     // the next frame to solve
  size_t written_ = 0;  // frames written
  int running_ = 0;     // jobs of this stream on the pool
  bool started_ = false, writing_ = false, finished_ = false;
  std::optional<grpc::Status> failed_;
  grpc::Status final_status_;
  grpc::ByteBuffer frame_;
};

}  // namespace

grpc::ServerWriteReactor<grpc::ByteBuffer>* NewSolveCall(grpc::CallbackServerContext* call, ServiceContext& context,
                                                         v1::SolveRequest request, Reservation& received) {
  return new SolveReactor(call, context, std::move(request), received);
}

}  // namespace springblend::server
