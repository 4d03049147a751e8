#include <spdlog/spdlog.h>

#include <atomic>
#include <chrono>
#include <memory>
#include <mutex>
#include <optional>

#include "call_support.h"
#include "calls.h"
#include "springblend/error.h"

namespace springblend::server {
namespace {

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
    info_ = BeginCall(call, "Interactive");
    info_.frames = 0;
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
    // The read just started may already have ended (the client half-closed, inline or on another thread) while
    // starting_read_ kept the session from finishing: whatever that callback could not do is done here.
    if (refused_) {
      FinishIfIdle(lock, *refused_);
    } else if (cancelled_) {
      FinishIfIdle(lock, StoppedStatus(*watch_, "the client cancelled the session"));
    } else {
      FinishIfDone(lock);
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
    info_.frames = received_;
    info_.character = start_.character_id();
    EndCall(context_.metrics, info_, status);
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
      if (!context_.pool.TrySubmit([this, busy = Busy()] { RunSolve(); }, true)) {
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
    if (context_.pool.SubmitContinuation([this, job, busy = Busy()] { (this->*job)(); }, true)) return true;
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
      const std::optional<grpc::Status> started = Start();
      lock.lock();
      if (!started) return;  // waiting for the character's build: solving_ stays, the session is busy
      const grpc::Status& status = *started;
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
      status = FrameStatus(e, entry_, context_);
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
      status = FrameStatus(e, entry_, context_);
    }
    lock.lock();
    previewing_ = false;
    Finished(lock, status, std::move(answer), false);
  }

  // The session's setup: nullopt while the character is being built (an upload, or a rebuild from the cache
  // directory), which the session waits for without holding a worker: the build's end queues RunSolve again.
  std::optional<grpc::Status> Start() {
    try {
      if (!looked_up_) {
        looked_up_ = true;
        CheckId(start_.character_id(), "start.character_id");
        CharacterStore::Found found = context_.store.Find(start_.character_id(), true, BuildWants(call_, context_));
        if (found.building) {
          waiter_ = std::move(found.waiter);
          found.building->OnDone([this, busy = Busy()](const std::shared_ptr<const CharacterStore::Entry>& entry,
                                                       std::exception_ptr error) {
            built_ = entry;
            build_error_ = error;
            if (!context_.pool.SubmitContinuation([this, busy] { RunSolve(); }, true)) RunSolve();
          });
          return std::nullopt;
        }
        built_ = found.entry;
      }
      waiter_.reset();
      if (build_error_) std::rethrow_exception(build_error_);
      entry_ = built_;
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
  CallInfo info_;
  OpenCall open_{context_.metrics.interactive_sessions};
  std::shared_ptr<Watchdog::Handle> watch_;
  Reservation memory_;
  SolverCharge solver_charge_;
  grpc::ByteBuffer bytes_;
  v1::InteractiveRequest incoming_;
  v1::InteractiveStart start_;
  std::shared_ptr<const CharacterStore::Entry> entry_;
  bool looked_up_ = false;                            // the character asked for (Start)
  CharacterStore::Waiter waiter_;                     // while it is being built
  std::shared_ptr<const CharacterStore::Entry> built_;  // the build's result, for the queued RunSolve
  std::exception_ptr build_error_;
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

grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>* NewInteractiveCall(grpc::CallbackServerContext* call,
                                                                               ServiceContext& context) {
  return new InteractiveReactor(call, context);
}

}  // namespace springblend::server
