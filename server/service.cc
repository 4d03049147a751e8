#include "service.h"

#include <grpcpp/support/byte_buffer.h>
#include <grpcpp/support/proto_buffer_reader.h>
#include <spdlog/spdlog.h>

#include <atomic>
#include <chrono>
#include <map>
#include <mutex>
#include <optional>

#include "springblend/error.h"
#include "status.h"

namespace springblend::server {
namespace {

const grpc::Status kQueueFull = QueueFull();

// The request bytes as a message; false when they do not parse.
template <typename Message>
bool Parse(const grpc::ByteBuffer& bytes, Message* message) {
  grpc::ByteBuffer copy(bytes);  // Deserialize consumes its buffer; copies share the slices
  return grpc::SerializationTraits<Message>::Deserialize(&copy, message).ok();
}

template <typename Message>
grpc::ByteBuffer Serialize(const Message& message) {
  grpc::ByteBuffer out;
  bool own = false;
  grpc::SerializationTraits<Message>::Serialize(message, &out, &own);
  return out;
}

// The token check every handler makes before any work; a refusal is counted like any other answer.
std::optional<grpc::Status> Refused(grpc::CallbackServerContext* call, ServiceContext& context, const char* method,
                                    Access needed) {
  const AuthVerdict verdict = context.auth.Check(*call, needed);
  if (verdict.allowed()) return std::nullopt;
  const grpc::Status status = ToStatus(verdict);
  context.metrics.CountRequest(method, CodeName(status.error_code()));
  return status;
}

// A streaming call refused before any work: it answers with the status and goes.
template <typename Reactor>
class Refusal final : public Reactor {
 public:
  explicit Refusal(const grpc::Status& status) { this->Finish(status); }
  void OnDone() override { delete this; }
};

// Parses the request, then runs `work(request, &response)` on the metadata pool and finishes the unary call with
// its status; refuses at once when the token does not allow the call, the bytes do not parse, or the queue is
// full.
template <typename Request, typename Response, typename Work>
grpc::ServerUnaryReactor* OnPool(grpc::CallbackServerContext* call, ServiceContext& context, const char* method,
                                 Access needed, const grpc::ByteBuffer* in, grpc::ByteBuffer* out, Work work) {
  SolverPool& pool = context.metadata_pool;
  grpc::ServerUnaryReactor* reactor = call->DefaultReactor();
  Metrics& metrics = context.metrics;
  if (auto refused = Refused(call, context, method, needed)) {
    reactor->Finish(*refused);
    return reactor;
  }
  auto request = std::make_shared<Request>();
  if (!Parse(*in, request.get())) {
    const grpc::Status status = Unparseable(Request::descriptor()->name());
    metrics.CountRequest(method, CodeName(status.error_code()));
    reactor->Finish(status);
    return reactor;
  }
  const bool queued = pool.TrySubmit([reactor, &metrics, method, request, out, work = std::move(work)]() mutable {
    grpc::Status status;
    try {
      Response response;
      status = work(*request, &response);
      if (status.ok()) *out = Serialize(response);
    } catch (const std::exception& e) {
      status = ToStatus(e);
    }
    metrics.CountRequest(method, CodeName(status.error_code()));
    reactor->Finish(status);
  });
  if (!queued) {
    metrics.CountRequest(method, CodeName(kQueueFull.error_code()));
    reactor->Finish(kQueueFull);
  }
  return reactor;
}

// The solvers a stream holds, in the memory budget (Solver::BytesFor each, reserved by the stream) and in the
// metrics' gauges; given back when the stream goes.
class SolverCharge {
 public:
  explicit SolverCharge(Metrics& metrics) : metrics_(metrics) {}
  ~SolverCharge() { metrics_.HoldSolvers(-solvers_, -bytes_); }
  SolverCharge(const SolverCharge&) = delete;
  SolverCharge& operator=(const SolverCharge&) = delete;
  // Reserves `count` solvers of `each` bytes in `memory` (at least `required`, the others as the budget has
  // room); returns how many. Throws LimitError when not even the required ones fit.
  int Reserve(Reservation& memory, std::int64_t each, int required, int count) {
    memory.Grow(each * required);
    int held = required;
    while (held < count && memory.TryGrow(each)) ++held;
    solvers_ += held;
    bytes_ += each * held;
    metrics_.HoldSolvers(held, each * held);
    return held;
  }

 private:
  Metrics& metrics_;
  int solvers_ = 0;
  std::int64_t bytes_ = 0;
};

grpc::Status StoppedStatus(const Watchdog::Handle& watch, const char* what) {
  if (const char* why = watch.expired()) return Cancelled(why);
  return Cancelled(what);
}

const grpc::Status kShuttingDown = ShuttingDown();

bool CallExpired(const grpc::CallbackServerContext& call) { return std::chrono::system_clock::now() > call.deadline(); }

// The stop check of a rig build a call waits for (its upload, or a rebuild from the cache directory): the
// client cancelled, the call's deadline passed, or the shutdown's drain is over. Another caller waiting for the
// same build is not stopped by it (CharacterStore builds it again for them).
StopCheck BuildStop(grpc::CallbackServerContext* call, const ServiceContext& context) {
  return [call, &context] { return call->IsCancelled() || CallExpired(*call) || context.drain.Passed(); };
}

// The status of an error from work that built with BuildStop: a stopped build says why it stopped.
grpc::Status BuildStatus(const std::exception& error, grpc::CallbackServerContext* call, const ServiceContext& context) {
  const auto* e = dynamic_cast<const Error*>(&error);
  if (e == nullptr || e->code() != ErrorCode::kCancelled) return ToStatus(error);
  if (context.drain.Passed()) return kShuttingDown;
  if (CallExpired(*call)) return DeadlineExceeded("the deadline passed while the character was being built");
  return Cancelled("the call was cancelled while the character was being built");
}

class UploadReactor final : public grpc::ServerReadReactor<grpc::ByteBuffer> {
 public:
  UploadReactor(grpc::CallbackServerContext* call, ServiceContext& context, grpc::ByteBuffer* response)
      : call_(call),
        context_(context),
        response_(response),
        watch_(context.watchdog.Watch(call, false)),
        assembler_(context.limits, &context.memory) {
    watch_->Waiting();
    StartRead(&bytes_);
  }

  void OnReadDone(bool ok) override {
    watch_->Progress();
    if (!ok) {
      if (call_->IsCancelled()) {
        Done(StoppedStatus(*watch_, "the upload was cancelled"));
        return;
      }
      Complete();
      return;
    }
    v1::UploadChunk chunk;
    if (!Parse(bytes_, &chunk)) {
      Done(Unparseable("UploadChunk"));
      return;
    }
    bytes_.Clear();
    try {
      assembler_.Add(chunk);
    } catch (const std::exception& e) {
      Done(ToStatus(e));
      return;
    }
    watch_->Waiting();
    StartRead(&bytes_);
  }
  void OnDone() override {
    watch_->Done();
    delete this;
  }

 private:
  void Done(const grpc::Status& status) {
    context_.metrics.CountRequest("UploadCharacter", CodeName(status.error_code()));
    Finish(status);
  }
  void Complete() {
    const bool queued = context_.pool.TrySubmit([this] {
      grpc::Status status;
      try {
        const auto [entry, known] = context_.store.Put(assembler_.Finish(), BuildStop(call_, context_));
        *response_ = Serialize(ToProto(*entry, known));
        spdlog::info("upload {} '{}': {} ({} vertices, {} springs, {:.0f} ms)", entry->id.substr(0, 12),
                     Printable(entry->name), known ? "cache hit" : "built", entry->rig->num_vertices(),
                     entry->rig->num_springs(), entry->rig->summary().precompute_ms);
      } catch (const std::exception& e) {
        status = BuildStatus(e, call_, context_);
        spdlog::warn("upload refused: {}", Printable(status.error_message(), 400));
      }
      Done(status);
    });
    if (!queued) Done(kQueueFull);
  }

  grpc::CallbackServerContext* call_;
  ServiceContext& context_;
  grpc::ByteBuffer* response_;
  std::shared_ptr<Watchdog::Handle> watch_;
  UploadAssembler assembler_;
  grpc::ByteBuffer bytes_;
};

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
  // On a pool worker: the request's conversion (its colliders once), then the first frames.
  void Start() {
    try {
      CheckId(request_.character_id(), "character_id");
      entry_ = context_.store.Get(request_.character_id(), BuildStop(call_, context_));
      if (!entry_) throw StatusError(NotFound(request_.character_id()));
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
      context_.metrics.CountRequest("Solve", CodeName(final_status_.error_code()));
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
        error = ToStatus(e);
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
  v1::SolveRequest request_;
  std::shared_ptr<Watchdog::Handle> watch_;
  Reservation memory_;
  SolverCharge solvers_charge_;
  std::int64_t request_bytes_ = 0;  // the parsed request, counted until converted
  std::shared_ptr<const CharacterStore::Entry> entry_;
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

// An interactive session. Frames arrive on gRPC threads and only replace the pending one; a pool job solves
// the newest pending frame, and, with previews, another pool job answers the newest frame at once with the
// rig's prediction (a few milliseconds) while a solve may still run. Answers wait in a two-slot outbox (the
// newest preview, the newest solve) and go out one write at a time, by increasing frame index; an answer
// older than one already sent is dropped (a solve overtaken by a newer frame's preview). No worker ever waits
// on the client: a job stores its answer and returns. The colliders are converted and the Solver made once, at
// the start, and live as long as the session; every frame is solved alone (stateless frames), so the settled
// answer equals a one-frame Solve of the same weights.
class InteractiveReactor final : public grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer> {
 public:
  InteractiveReactor(grpc::CallbackServerContext* call, ServiceContext& context)
      : call_(call),
        context_(context),
        watch_(context.watchdog.Watch(call, true)),
        memory_(&context.memory),
        solver_charge_(context.metrics) {
    StartRead(&bytes_);
  }

  void OnReadDone(bool ok) override {
    watch_->Activity();
    std::unique_lock lock(mutex_);
    if (finished_) return;
    if (!ok) {
      reads_done_ = true;
      if (cancelled_) {
        FinishIfIdle(lock, StoppedStatus(*watch_, "the client cancelled the session"));
      } else {
        FinishIfDone(lock);
      }
      Act(lock);
      return;
    }
    if (!Parse(bytes_, &incoming_)) {
      Refuse(lock, Unparseable("InteractiveRequest"));
      Act(lock);
      return;
    }
    bytes_.Clear();
    if (!started_) {
      if (!incoming_.has_start()) {
        Refuse(lock, BadMessage("the first message must be a start message"));
        Act(lock);
        return;
      }
      started_ = true;
      start_ = incoming_.start();
      previews_ = start_.previews();
    } else if (incoming_.has_frame()) {
      if (pending_) ++dropped_;
      const std::uint32_t index = received_++;
      newest_.store(index, std::memory_order_relaxed);
      if (previews_) to_preview_ = Job{*incoming_.mutable_frame(), index};
      pending_ = Job{std::move(*incoming_.mutable_frame()), index};
    } else {
      Refuse(lock, BadMessage("only the first message may be a start message"));
      Act(lock);
      return;
    }
    if (!Schedule(lock)) {
      Act(lock);
      return;
    }
    // Nothing may finish the session while the next read is being started (the reactor must outlive the
    // call); once it is outstanding, gRPC holds the reactor until it completes.
    starting_read_ = true;
    lock.unlock();
    StartRead(&bytes_);
    lock.lock();
    starting_read_ = false;
    if (refused_) {
      FinishIfIdle(lock, *refused_);
    } else if (cancelled_) {
      FinishIfIdle(lock, StoppedStatus(*watch_, "the client cancelled the session"));
    }
    Act(lock);
  }

  void OnWriteDone(bool ok) override {
    watch_->Progress();
    std::unique_lock lock(mutex_);
    writing_ = false;
    if (!ok) cancelled_ = true;
    if (refused_) {
      FinishIfIdle(lock, *refused_);
    } else if (cancelled_) {
      Clear();
      FinishIfIdle(lock, StoppedStatus(*watch_, "the client cancelled the session"));
    } else {
      Flush(lock);
      Schedule(lock);
      FinishIfDone(lock);
    }
    Act(lock);
  }
  void OnCancel() override {
    std::unique_lock lock(mutex_);
    cancelled_ = true;
    Clear();
    FinishIfIdle(lock, StoppedStatus(*watch_, "the client cancelled the session"));
    Act(lock);
  }
  void OnDone() override {
    watch_->Done();
    delete this;
  }

 private:
  struct Job {
    v1::FrameRequest frame;
    std::uint32_t index = 0;
  };
  struct Answer {
    grpc::ByteBuffer bytes;
    std::uint32_t index = 0;
  };

  // All with mutex_ held. The session is finished exactly once, never while a job runs, a write is in flight
  // or a read is being started; the gRPC calls (Finish, StartWrite) are made by Act, after the lock is let go,
  // as the last thing a callback or job does: after them the reactor may be gone.
  void FinishLocked(std::unique_lock<std::mutex>&, const grpc::Status& status) {
    if (finished_) return;
    finished_ = true;
    context_.metrics.CountRequest("Interactive", CodeName(status.error_code()));
    finish_due_ = status;
  }
  void Act(std::unique_lock<std::mutex>& lock) {
    std::optional<grpc::Status> finish = std::move(finish_due_);
    finish_due_.reset();
    const bool write = write_due_;
    write_due_ = false;
    lock.unlock();
    if (finish) {
      Finish(*finish);
    } else if (write) {
      StartWrite(&out_);
    }
  }
  bool Idle() const { return !solving_ && !previewing_ && !writing_ && !starting_read_; }
  void FinishIfIdle(std::unique_lock<std::mutex>& lock, const grpc::Status& status) {
    if (Idle()) FinishLocked(lock, status);
  }
  // The client half-closed and every frame it sent is answered (or overtaken): the stream ends OK.
  void FinishIfDone(std::unique_lock<std::mutex>& lock) {
    if (reads_done_ && !pending_ && !to_preview_ && !outbox_preview_ && !outbox_solved_) {
      FinishIfIdle(lock, grpc::Status::OK);
    }
  }
  void Clear() {
    pending_.reset();
    to_preview_.reset();
    outbox_preview_.reset();
    outbox_solved_.reset();
  }
  // A bad message: finish now, or, while a job runs or a write is in flight, when that ends. Reading stops.
  void Refuse(std::unique_lock<std::mutex>& lock, const grpc::Status& status) {
    Clear();
    if (!refused_) refused_ = status;
    FinishIfIdle(lock, status);
  }
  // A job failed: the session ends with its status once nothing else runs.
  void Fail(std::unique_lock<std::mutex>& lock, const grpc::Status& status) { Refuse(lock, status); }

  // Queues the jobs there is work for: the setup (with the first frame's solve), a solve of the newest frame
  // when none runs, a preview of the newest frame when none runs (each unless its answer would only replace
  // one already waiting behind the write in flight). False (and the session finished) when the
  // queue refuses the session's first job.
  bool Schedule(std::unique_lock<std::mutex>& lock) {
    if (cancelled_ || refused_ || finished_) return true;
    if (!setup_requested_) {
      setup_requested_ = true;
      solving_ = true;
      if (!context_.pool.TrySubmit([this, busy = Busy()] { RunSolve(); })) {
        solving_ = false;
        Clear();
        FinishLocked(lock, kQueueFull);
        return false;
      }
      return true;
    }
    if (!ready_) return true;  // the setup job is still running; it schedules again when done
    // At most one answer of each kind waits behind the write in flight: a client that stops reading stops the
    // session's work (its newest frame is solved when the write completes), so it holds no worker.
    if (pending_ && !solving_ && !(writing_ && outbox_solved_) &&
        !Submit(lock, &solving_, &InteractiveReactor::RunSolve)) {
      return false;
    }
    if (to_preview_ && !previewing_ && !(writing_ && outbox_preview_) &&
        !Submit(lock, &previewing_, &InteractiveReactor::RunPreview)) {
      return false;
    }
    return true;
  }
  // Queues one more job of the session, marking it running; false (the session ends) when the pool refuses.
  bool Submit(std::unique_lock<std::mutex>& lock, bool* running, void (InteractiveReactor::*job)()) {
    *running = true;
    if (context_.pool.SubmitContinuation([this, job, busy = Busy()] { (this->*job)(); })) return true;
    *running = false;
    Clear();
    refused_ = kShuttingDown;
    FinishIfIdle(lock, kShuttingDown);
    return false;
  }

  // The session is busy (not idle, whatever --idle-seconds says) from a job's submission until its function
  // goes, after the job's last act: the token holds the watchdog's handle, which outlives the reactor.
  std::shared_ptr<void> Busy() {
    std::shared_ptr<Watchdog::Handle> watch = watch_;
    watch->Busy();
    return std::shared_ptr<void>(nullptr, [watch](void*) { watch->Unbusy(); });
  }

  // Starts the next write, if none is in flight: the outbox's answer of the lower frame index first; an answer
  // older than one already sent is dropped.
  void Flush(std::unique_lock<std::mutex>&) {
    if (writing_ || cancelled_ || refused_ || finished_) return;
    const auto stale = [this](const std::optional<Answer>& a, bool solved) {
      if (!a || !sent_any_) return false;
      return solved ? (a->index < sent_index_ || (a->index == sent_index_ && sent_solved_)) : a->index <= sent_index_;
    };
    if (stale(outbox_solved_, true)) outbox_solved_.reset();
    if (stale(outbox_preview_, false)) outbox_preview_.reset();
    std::optional<Answer>* next = nullptr;
    bool solved = false;
    if (outbox_solved_ && (!outbox_preview_ || outbox_solved_->index <= outbox_preview_->index)) {
      next = &outbox_solved_;
      solved = true;
    } else if (outbox_preview_) {
      next = &outbox_preview_;
    }
    if (next == nullptr) return;
    out_ = std::move((*next)->bytes);
    if (!sent_any_ || (*next)->index > sent_index_) sent_solved_ = false;
    sent_index_ = (*next)->index;
    sent_any_ = true;
    if (solved) {
      sent_solved_ = true;
      // A preview of the frame just solved says nothing new.
      if (outbox_preview_ && outbox_preview_->index <= sent_index_) outbox_preview_.reset();
    }
    next->reset();
    writing_ = true;
    write_due_ = true;
    watch_->Waiting();
  }

  // After a job, its last act (with the lock held; lets it go): store its answer, write, schedule more, or end
  // the session.
  void Finished(std::unique_lock<std::mutex>& lock, const grpc::Status& status, std::optional<Answer> answer,
                bool solved) {
    Store(lock, status, std::move(answer), solved);
    Act(lock);
  }
  void Store(std::unique_lock<std::mutex>& lock, const grpc::Status& status, std::optional<Answer> answer,
             bool solved) {
    if (!status.ok()) {
      Fail(lock, status);
      return;
    }
    if (cancelled_ || refused_) {
      FinishIfIdle(lock, refused_ ? *refused_ : StoppedStatus(*watch_, "the client cancelled the session"));
      return;
    }
    if (answer) {
      std::optional<Answer>& slot = solved ? outbox_solved_ : outbox_preview_;
      if (!slot || slot->index < answer->index) slot = std::move(answer);
    }
    Flush(lock);
    Schedule(lock);
    FinishIfDone(lock);
  }

  // On a pool worker: the setup (first time), then the newest pending frame's solve.
  void RunSolve() {
    std::unique_lock lock(mutex_);
    if (!ready_) {
      lock.unlock();
      grpc::Status status = Start();
      lock.lock();
      if (!status.ok()) {
        solving_ = false;
        Finished(lock, status, std::nullopt, true);
        return;
      }
      ready_ = true;
      Schedule(lock);  // a preview of the newest frame beside this solve
    }
    if (!pending_ || cancelled_ || refused_) {
      solving_ = false;
      Finished(lock, grpc::Status::OK, std::nullopt, true);
      return;
    }
    Job job = std::move(*pending_);
    pending_.reset();
    lock.unlock();
    grpc::Status status;
    std::optional<Answer> answer;
    try {
      const Frame frame = ToFrame(job.frame, *entry_->rig, colliders_, job.index);
      Points positions;
      // Stop when the session is cancelled, and, with previews (the client has something to show), when a
      // newer frame overtakes this one: its solve starts at once instead of after this one.
      const SolveSummary summary = solver_->Solve(frame, &positions, [this, &job] {
        return call_->IsCancelled() || (previews_ && newest_.load(std::memory_order_relaxed) > job.index);
      });
      if (summary.termination != Termination::kCancelled) {
        context_.metrics.CountFrame(summary.solve_ms / 1000.0, summary.newton_iterations, summary.converged());
        CheckSolved(positions, job.index);
        answer = Answer{Serialize(ToProto(static_cast<int>(job.index), positions, entry_->rig->rest().faces,
                                          summary, job_.with_normals, context_.replica_name)),
                        job.index};
      }
    } catch (const std::exception& e) {
      status = ToStatus(e);
    }
    lock.lock();
    solving_ = false;
    // The solve covers its frame: a preview not yet made for it (or an older one) is not needed.
    if (to_preview_ && to_preview_->index <= job.index) to_preview_.reset();
    Finished(lock, status, std::move(answer), true);
  }

  // On a pool worker: the newest frame's preview, the rig's prediction for its weights (Solver::Start reads
  // only the rig and the options, so it may run beside the session's solve).
  void RunPreview() {
    std::unique_lock lock(mutex_);
    if (!to_preview_ || cancelled_ || refused_) {
      previewing_ = false;
      Finished(lock, grpc::Status::OK, std::nullopt, false);
      return;
    }
    Job job = std::move(*to_preview_);
    to_preview_.reset();
    lock.unlock();
    grpc::Status status;
    std::optional<Answer> answer;
    try {
      const auto start = std::chrono::steady_clock::now();
      const Frame frame = ToFrame(job.frame, *entry_->rig, colliders_, job.index);
      const Points positions = solver_->Start(frame.weights).topRows(entry_->rig->num_surface_vertices());
      CheckSolved(positions, job.index);
      SolveSummary summary;
      summary.termination = Termination::kMaxIterations;
      summary.finish = Finish::kNone;
      summary.message = "preview: the rig's prediction for these weights (colliders and pins not yet solved)";
      summary.solve_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
      v1::SolvedFrame preview = ToProto(static_cast<int>(job.index), positions, entry_->rig->rest().faces, summary,
                                        job_.with_normals, context_.replica_name);
      preview.mutable_summary()->set_termination("preview");
      answer = Answer{Serialize(preview), job.index};
    } catch (const std::exception& e) {
      status = ToStatus(e);
    }
    lock.lock();
    previewing_ = false;
    Finished(lock, status, std::move(answer), false);
  }

  grpc::Status Start() {
    try {
      CheckId(start_.character_id(), "start.character_id");
      entry_ = context_.store.Get(start_.character_id(), BuildStop(call_, context_));
      if (!entry_) return NotFound(start_.character_id());
      memory_.Grow(StreamBytes(start_.colliders()));
      ToOptions(start_.options(), &job_);
      // The session's Solver, for as long as the session lives.
      solver_charge_.Reserve(memory_, Solver::BytesFor(*entry_->rig, job_.options), 1, 1);
      std::vector<Collider> colliders =
          ToColliders(start_.colliders(), context_.limits, [this] { return call_->IsCancelled(); });
      colliders_ = colliders.size();
      context_.metrics.CountColliders(colliders.size());
      solver_ = std::make_unique<Solver>(entry_->rig, job_.options);
      solver_->SetColliders(std::move(colliders));
      start_.clear_colliders();  // converted once; the text is not needed again
    } catch (const std::exception& e) {
      return BuildStatus(e, call_, context_);
    }
    return grpc::Status::OK;
  }

  grpc::CallbackServerContext* call_;
  ServiceContext& context_;
  std::shared_ptr<Watchdog::Handle> watch_;
  Reservation memory_;
  SolverCharge solver_charge_;
  grpc::ByteBuffer bytes_;
  v1::InteractiveRequest incoming_;
  v1::InteractiveStart start_;
  std::shared_ptr<const CharacterStore::Entry> entry_;
  SolveJob job_;  // options only
  size_t colliders_ = 0;
  std::unique_ptr<Solver> solver_;
  grpc::ByteBuffer out_;
  std::optional<Job> pending_;     // the newest frame not yet taken by a solve
  std::optional<Job> to_preview_;  // the newest frame not yet previewed (previews only)
  std::optional<Answer> outbox_preview_, outbox_solved_;  // answers waiting for the write in flight
  std::uint32_t sent_index_ = 0;                          // the newest frame index written so far
  bool sent_any_ = false, sent_solved_ = false;           // and whether its solve was
  bool previews_ = false;                                 // InteractiveStart.previews
  std::optional<grpc::Status> refused_;  // a bad message or a failed job: the session ends with it
  std::uint32_t received_ = 0, dropped_ = 0;
  std::atomic<std::uint32_t> newest_{0};  // the newest frame's index, read by a running solve's stop check
  std::mutex mutex_;  // guards the session's state below and above
  bool started_ = false, setup_requested_ = false, ready_ = false, solving_ = false, previewing_ = false,
       writing_ = false, reads_done_ = false, cancelled_ = false, finished_ = false, starting_read_ = false,
       write_due_ = false;
  std::optional<grpc::Status> finish_due_;  // Act's to do
};

}  // namespace

grpc::ServerReadReactor<grpc::ByteBuffer>* CharacterServiceImpl::UploadCharacter(grpc::CallbackServerContext* call,
                                                                                 grpc::ByteBuffer* response) {
  if (auto refused = Refused(call, context_, "UploadCharacter", Access::kWrite)) {
    return new Refusal<grpc::ServerReadReactor<grpc::ByteBuffer>>(*refused);
  }
  return new UploadReactor(call, context_, response);
}

grpc::ServerUnaryReactor* CharacterServiceImpl::GetCharacter(grpc::CallbackServerContext* call,
                                                             const grpc::ByteBuffer* in, grpc::ByteBuffer* out) {
  return OnPool<v1::GetCharacterRequest, v1::Character>(
      call, context_, "GetCharacter", Access::kRead, in, out,
      [this, call](const v1::GetCharacterRequest& request, v1::Character* response) -> grpc::Status {
        CheckId(request.id(), "id");
        std::shared_ptr<const CharacterStore::Entry> entry;
        try {
          entry = context_.store.Get(request.id(), BuildStop(call, context_));
        } catch (const std::exception& e) {
          return BuildStatus(e, call, context_);
        }
        if (!entry) return NotFound(request.id());
        *response = ToProto(*entry, true);
        response->clear_cache_hit();
        if (request.with_faces()) {
          const Faces& faces = entry->rig->rest().faces;
          response->set_faces(reinterpret_cast<const char*>(faces.data()), sizeof(int) * static_cast<size_t>(faces.size()));
        }
        return grpc::Status::OK;
      });
}

grpc::ServerUnaryReactor* CharacterServiceImpl::ListCharacters(grpc::CallbackServerContext* call,
                                                               const grpc::ByteBuffer* in, grpc::ByteBuffer* out) {
  return OnPool<v1::ListCharactersRequest, v1::ListCharactersResponse>(
      call, context_, "ListCharacters", Access::kRead, in, out,
      [this](const v1::ListCharactersRequest&, v1::ListCharactersResponse* response) -> grpc::Status {
        for (const auto& listed : context_.store.List()) {
          v1::Character* c = response->add_characters();
          if (listed.entry) {
            *c = ToProto(*listed.entry, true);
            c->clear_cache_hit();
          } else {  // in the cache directory, not built yet: GetCharacter builds it
            c->set_id(listed.id);
            c->set_name(listed.name);
          }
        }
        return grpc::Status::OK;
      });
}

grpc::ServerUnaryReactor* CharacterServiceImpl::DeleteCharacter(grpc::CallbackServerContext* call,
                                                                const grpc::ByteBuffer* in, grpc::ByteBuffer* out) {
  return OnPool<v1::DeleteCharacterRequest, v1::DeleteCharacterResponse>(
      call, context_, "DeleteCharacter", Access::kWrite, in, out,
      [this](const v1::DeleteCharacterRequest& request, v1::DeleteCharacterResponse*) -> grpc::Status {
        CheckId(request.id(), "id");
        if (!context_.store.Delete(request.id())) return NotFound(request.id());
        spdlog::info("deleted {}", request.id().substr(0, 12));
        return grpc::Status::OK;
      });
}

grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>* SolveServiceImpl::Interactive(
    grpc::CallbackServerContext* call) {
  if (auto refused = Refused(call, context_, "Interactive", Access::kRead)) {
    return new Refusal<grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>>(*refused);
  }
  return new InteractiveReactor(call, context_);
}

grpc::ServerWriteReactor<grpc::ByteBuffer>* SolveServiceImpl::Solve(grpc::CallbackServerContext* call,
                                                                    const grpc::ByteBuffer* in) {
  using Refuse = Refusal<grpc::ServerWriteReactor<grpc::ByteBuffer>>;
  if (auto refused = Refused(call, context_, "Solve", Access::kRead)) return new Refuse(*refused);
  // The bytes gRPC received are counted until parsed (a request of pins parses to several times its size).
  Reservation received(&context_.memory);
  try {
    received.Grow(static_cast<std::int64_t>(in->Length()));
  } catch (const std::exception& e) {
    const grpc::Status status = ToStatus(e);
    context_.metrics.CountRequest("Solve", CodeName(status.error_code()));
    return new Refuse(status);
  }
  v1::SolveRequest request;
  if (!Parse(*in, &request)) {
    const grpc::Status status = Unparseable("SolveRequest");
    context_.metrics.CountRequest("Solve", CodeName(status.error_code()));
    return new Refuse(status);
  }
  // gRPC keeps the request's bytes for the whole call; parsed, they are not needed (the buffer is the call's,
  // not const, and is only destroyed after this).
  const_cast<grpc::ByteBuffer*>(in)->Clear();
  return new SolveReactor(call, context_, std::move(request), received);
}

}  // namespace springblend::server
