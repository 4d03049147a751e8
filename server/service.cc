#include "service.h"

#include <spdlog/spdlog.h>

#include <chrono>
#include <condition_variable>
#include <mutex>
#include <optional>

#include "springblend/error.h"
#include "status.h"

namespace springblend::server {
namespace {

const char* CodeName(grpc::StatusCode code) {
  switch (code) {
    case grpc::StatusCode::OK: return "OK";
    case grpc::StatusCode::CANCELLED: return "CANCELLED";
    case grpc::StatusCode::INVALID_ARGUMENT: return "INVALID_ARGUMENT";
    case grpc::StatusCode::DEADLINE_EXCEEDED: return "DEADLINE_EXCEEDED";
    case grpc::StatusCode::NOT_FOUND: return "NOT_FOUND";
    case grpc::StatusCode::RESOURCE_EXHAUSTED: return "RESOURCE_EXHAUSTED";
    case grpc::StatusCode::UNAUTHENTICATED: return "UNAUTHENTICATED";
    case grpc::StatusCode::PERMISSION_DENIED: return "PERMISSION_DENIED";
    case grpc::StatusCode::INTERNAL: return "INTERNAL";
    default: return "OTHER";
  }
}

const grpc::Status kQueueFull(grpc::StatusCode::RESOURCE_EXHAUSTED,
                              "the server's solve queue is full; retry later or add replicas");

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

// Runs `work` on the pool and finishes the unary call with its status; refuses at once when the token does not
// allow the call or the queue is full.
template <typename Work>
grpc::ServerUnaryReactor* OnPool(grpc::CallbackServerContext* call, ServiceContext& context, const char* method,
                                 Access needed, Work work) {
  grpc::ServerUnaryReactor* reactor = call->DefaultReactor();
  if (auto refused = Refused(call, context, method, needed)) {
    reactor->Finish(*refused);
    return reactor;
  }
  Metrics& metrics = context.metrics;
  const bool queued = context.pool.TrySubmit([reactor, &metrics, method, work = std::move(work)]() mutable {
    grpc::Status status;
    try {
      status = work();
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

grpc::Status NotFound(const std::string& id) {
  return {grpc::StatusCode::NOT_FOUND,
          "no character with id '" + id + "' on this server or in its cache directory; upload it first"};
}

// The hand-over between a pool job that produces frames and gRPC, which sends them: one write in flight per
// stream, and the job waits until it is sent (or the stream is cancelled) before it goes on.
struct WriteGate {
  std::mutex mutex;
  std::condition_variable wake;
  bool writing = false;
  bool cancelled = false;

  void WriteDone(bool ok) {
    std::lock_guard lock(mutex);
    writing = false;
    if (!ok) cancelled = true;
    wake.notify_all();
  }
  void Cancel() {
    std::lock_guard lock(mutex);
    cancelled = true;
    wake.notify_all();
  }
  // With `lock` on mutex: marks a write in flight, lets `start` begin it unlocked, and waits until gRPC has
  // completed it (gRPC completes every started write, also on cancellation).
  template <typename Start>
  void Write(std::unique_lock<std::mutex>& lock, Start start) {
    writing = true;
    lock.unlock();
    start();
    lock.lock();
    wake.wait(lock, [this] { return !writing; });
  }
};

class UploadReactor final : public grpc::ServerReadReactor<v1::UploadChunk> {
 public:
  UploadReactor(grpc::CallbackServerContext* call, ServiceContext& context, v1::Character* response)
      : call_(call), context_(context), response_(response), assembler_(context.limits) {
    StartRead(&chunk_);
  }

  void OnReadDone(bool ok) override {
    if (!ok) {
      if (call_->IsCancelled()) {
        Done({grpc::StatusCode::CANCELLED, "the upload was cancelled"});
        return;
      }
      Complete();
      return;
    }
    try {
      assembler_.Add(chunk_);
    } catch (const std::exception& e) {
      const grpc::Status status = ToStatus(e);
      Done(assembler_.over_limit() ? grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED, status.error_message())
                                     : status);
      return;
    }
    StartRead(&chunk_);
  }
  void OnDone() override { delete this; }

 private:
  void Done(const grpc::Status& status) {
    context_.metrics.CountRequest("UploadCharacter", CodeName(status.error_code()));
    Finish(status);
  }
  void Complete() {
    const bool queued = context_.pool.TrySubmit([this] {
      grpc::Status status;
      try {
        const auto [entry, known] = context_.store.Put(assembler_.Finish());
        *response_ = ToProto(*entry, known);
        spdlog::info("upload {} '{}': {} ({} vertices, {} springs, {:.0f} ms)", entry->id.substr(0, 12),
                     entry->name, known ? "cache hit" : "built", entry->rig->num_vertices(),
                     entry->rig->num_springs(), entry->rig->summary().precompute_ms);
      } catch (const std::exception& e) {
        status = ToStatus(e);
        spdlog::warn("upload refused: {}", status.error_message());
      }
      Done(status);
    });
    if (!queued) Done(kQueueFull);
  }

  grpc::CallbackServerContext* call_;
  ServiceContext& context_;
  v1::Character* response_;
  UploadAssembler assembler_;
  v1::UploadChunk chunk_;
};

// Streams one frame at a time: a pool worker solves a frame, hands it over, and waits until gRPC has sent
// it before solving the next, so a slow reader holds at most one frame in the server.
class SolveReactor final : public grpc::ServerWriteReactor<v1::SolvedFrame> {
 public:
  SolveReactor(grpc::CallbackServerContext* call, ServiceContext& context, const v1::SolveRequest* request)
      : call_(call), context_(context), request_(request) {
    if (!context_.pool.TrySubmit([this] { Run(); })) Done(kQueueFull);
  }

  void OnWriteDone(bool ok) override { gate_.WriteDone(ok); }
  void OnCancel() override { gate_.Cancel(); }
  void OnDone() override { delete this; }

 private:
  void Done(const grpc::Status& status) {
    context_.metrics.CountRequest("Solve", CodeName(status.error_code()));
    Finish(status);
  }
  // On a pool worker. Finish is the last thing it does: OnDone (and delete) may follow at once.
  void Run() {
    const auto entry = context_.store.Get(request_->character_id());
    if (!entry) {
      Done(NotFound(request_->character_id()));
      return;
    }
    SolveJob job;
    try {
      job = ToSolveJob(*request_, *entry->rig, context_.limits);
    } catch (const std::exception& e) {
      Done(ToStatus(e));
      return;
    }
    try {
      Solver solver(entry->rig, job.options);
      solver.SetColliders(std::move(job.colliders));
      Points positions;
      for (size_t i = 0; i < job.frames.size(); ++i) {
        if (Stopped()) {
          Done(Expired() ? grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED, fmt::format("deadline passed after {} of {} frames", i, job.frames.size()))
                           : grpc::Status(grpc::StatusCode::CANCELLED, "the client cancelled the stream"));
          return;
        }
        const SolveSummary summary = solver.Solve(job.frames[i], &positions);
        context_.metrics.CountFrame(summary.solve_ms / 1000.0, summary.newton_iterations, summary.converged());
        frame_ = ToProto(static_cast<int>(i), positions, entry->rig->rest().faces, summary, job.with_normals,
                         context_.replica_name);
        std::unique_lock lock(gate_.mutex);
        gate_.Write(lock, [this] { StartWrite(&frame_); });
      }
    } catch (const std::exception& e) {
      Done(ToStatus(e));
      return;
    }
    Done(grpc::Status::OK);
  }

  bool Expired() const { return std::chrono::system_clock::now() > call_->deadline(); }
  bool Stopped() {
    std::lock_guard lock(gate_.mutex);
    return gate_.cancelled || Expired();
  }

  grpc::CallbackServerContext* call_;
  ServiceContext& context_;
  const v1::SolveRequest* request_;
  v1::SolvedFrame frame_;
  WriteGate gate_;
};

// An interactive session. Frames arrive on gRPC threads and only replace the pending one; a pool job solves
// whatever is pending, newest first, and gives its worker back as soon as nothing is. The Solver (and with
// it the warm start) lives as long as the session.
class InteractiveReactor final : public grpc::ServerBidiReactor<v1::InteractiveRequest, v1::SolvedFrame> {
 public:
  InteractiveReactor(grpc::CallbackServerContext* call, ServiceContext& context) : call_(call), context_(context) {
    StartRead(&incoming_);
  }

  void OnReadDone(bool ok) override {
    std::unique_lock lock(mutex_);
    if (finished_) return;
    if (!ok) {
      reads_done_ = true;
      FinishIfIdle(lock, grpc::Status::OK);
      return;
    }
    if (!started_) {
      if (!incoming_.has_start()) {
        Refuse(lock, {grpc::StatusCode::INVALID_ARGUMENT, "the first message must be a start message"});
        return;
      }
      started_ = true;
      start_ = incoming_.start();
    } else if (incoming_.has_frame()) {
      if (pending_) ++dropped_;
      pending_ = incoming_.frame();
      pending_index_ = received_++;
    } else {
      Refuse(lock, {grpc::StatusCode::INVALID_ARGUMENT, "only the first message may be a start message"});
      return;
    }
    if (!job_running_ && (pending_ || !setup_requested_)) {
      setup_requested_ = true;
      job_running_ = true;
      if (!context_.pool.TrySubmit([this] { Work(); })) {
        job_running_ = false;
        FinishLocked(lock, kQueueFull);
        return;
      }
    }
    lock.unlock();
    StartRead(&incoming_);
  }

  void OnWriteDone(bool ok) override { gate_.WriteDone(ok); }
  void OnCancel() override {
    std::unique_lock lock(mutex_);
    gate_.cancelled = true;
    gate_.wake.notify_all();
    FinishIfIdle(lock, {grpc::StatusCode::CANCELLED, "the client cancelled the session"});
  }
  void OnDone() override { delete this; }

 private:
  // Both with mutex_ held. Finish is called exactly once, and never while a job runs.
  void FinishLocked(std::unique_lock<std::mutex>&, const grpc::Status& status) {
    if (finished_) return;
    finished_ = true;
    context_.metrics.CountRequest("Interactive", CodeName(status.error_code()));
    Finish(status);
  }
  void FinishIfIdle(std::unique_lock<std::mutex>& lock, const grpc::Status& status) {
    if (!job_running_ && !pending_) FinishLocked(lock, status);
  }
  // A bad message: finish now, or, while a job runs (it may still use this reactor), let the job finish
  // with the refusal when it stops. Reading stops either way.
  void Refuse(std::unique_lock<std::mutex>& lock, const grpc::Status& status) {
    pending_.reset();
    if (job_running_) {
      refused_ = status;
    } else {
      FinishLocked(lock, status);
    }
  }

  void Work() {
    std::unique_lock lock(mutex_);
    if (!solver_) {
      lock.unlock();
      grpc::Status status = Start();
      lock.lock();
      if (!status.ok()) {
        job_running_ = false;
        pending_.reset();
        FinishLocked(lock, status);
        return;
      }
    }
    while (pending_ && !gate_.cancelled && !refused_) {
      const v1::FrameRequest request = std::move(*pending_);
      const std::uint32_t index = pending_index_;
      pending_.reset();
      lock.unlock();
      grpc::Status status;
      try {
        Frame frame = ToFrame(request);
        Points positions;
        const SolveSummary summary = solver_->Solve(frame, &positions);
        context_.metrics.CountFrame(summary.solve_ms / 1000.0, summary.newton_iterations, summary.converged());
        out_ = ToProto(static_cast<int>(index), positions, entry_->rig->rest().faces, summary, job_.with_normals,
                       context_.replica_name);
      } catch (const std::exception& e) {
        status = ToStatus(e);
      }
      lock.lock();
      if (!status.ok()) {
        job_running_ = false;
        pending_.reset();
        FinishLocked(lock, status);
        return;
      }
      gate_.Write(lock, [this] { StartWrite(&out_); });
    }
    job_running_ = false;
    if (refused_) {
      FinishLocked(lock, *refused_);
    } else if (gate_.cancelled) {
      pending_.reset();
      FinishLocked(lock, {grpc::StatusCode::CANCELLED, "the client cancelled the session"});
    } else if (reads_done_) {
      FinishIfIdle(lock, grpc::Status::OK);
    }
  }

  grpc::Status Start() {
    entry_ = context_.store.Get(start_.character_id());
    if (!entry_) return NotFound(start_.character_id());
    try {
      // Reuse the request conversion with one neutral frame to check colliders and options.
      v1::SolveRequest probe;
      *probe.mutable_colliders() = start_.colliders();
      *probe.mutable_options() = start_.options();
      probe.add_frames()->mutable_weights()->Resize(entry_->rig->num_targets(), 0.0);
      job_ = ToSolveJob(probe, *entry_->rig, context_.limits);
      solver_ = std::make_unique<Solver>(entry_->rig, job_.options);
      solver_->SetColliders(job_.colliders);
    } catch (const std::exception& e) {
      return ToStatus(e);
    }
    return grpc::Status::OK;
  }

  Frame ToFrame(const v1::FrameRequest& request) const {
    v1::SolveRequest one;
    *one.mutable_colliders() = start_.colliders();
    *one.add_frames() = request;
    return ToSolveJob(one, *entry_->rig, context_.limits).frames.front();
  }

  grpc::CallbackServerContext* call_;
  ServiceContext& context_;
  v1::InteractiveRequest incoming_;
  v1::InteractiveStart start_;
  std::shared_ptr<const CharacterStore::Entry> entry_;
  SolveJob job_;
  std::unique_ptr<Solver> solver_;
  v1::SolvedFrame out_;
  std::optional<v1::FrameRequest> pending_;
  std::optional<grpc::Status> refused_;  // a bad message arrived while a job ran
  std::uint32_t pending_index_ = 0, received_ = 0, dropped_ = 0;
  WriteGate gate_;
  std::mutex& mutex_ = gate_.mutex;  // one lock guards the session's state and its writes
  bool started_ = false, setup_requested_ = false, job_running_ = false, reads_done_ = false, finished_ = false;
};

}  // namespace

grpc::ServerReadReactor<v1::UploadChunk>* CharacterServiceImpl::UploadCharacter(grpc::CallbackServerContext* call,
                                                                                v1::Character* response) {
  if (auto refused = Refused(call, context_, "UploadCharacter", Access::kWrite)) {
    return new Refusal<grpc::ServerReadReactor<v1::UploadChunk>>(*refused);
  }
  return new UploadReactor(call, context_, response);
}

grpc::ServerUnaryReactor* CharacterServiceImpl::GetCharacter(grpc::CallbackServerContext* call,
                                                             const v1::GetCharacterRequest* request,
                                                             v1::Character* response) {
  return OnPool(call, context_, "GetCharacter", Access::kRead, [this, request, response]() -> grpc::Status {
    const auto entry = context_.store.Get(request->id());
    if (!entry) return NotFound(request->id());
    *response = ToProto(*entry, true);
    response->clear_cache_hit();
    if (request->with_faces()) {
      const Faces& faces = entry->rig->rest().faces;
      response->set_faces(reinterpret_cast<const char*>(faces.data()), sizeof(int) * static_cast<size_t>(faces.size()));
    }
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* CharacterServiceImpl::ListCharacters(grpc::CallbackServerContext* call,
                                                               const v1::ListCharactersRequest*,
                                                               v1::ListCharactersResponse* response) {
  return OnPool(call, context_, "ListCharacters", Access::kRead, [this, response]() -> grpc::Status {
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
                                                                const v1::DeleteCharacterRequest* request,
                                                                v1::DeleteCharacterResponse*) {
  return OnPool(call, context_, "DeleteCharacter", Access::kWrite, [this, request]() -> grpc::Status {
    if (!context_.store.Delete(request->id())) return NotFound(request->id());
    spdlog::info("deleted {}", request->id().substr(0, 12));
    return grpc::Status::OK;
  });
}

grpc::ServerBidiReactor<v1::InteractiveRequest, v1::SolvedFrame>* SolveServiceImpl::Interactive(
    grpc::CallbackServerContext* call) {
  if (auto refused = Refused(call, context_, "Interactive", Access::kRead)) {
    return new Refusal<grpc::ServerBidiReactor<v1::InteractiveRequest, v1::SolvedFrame>>(*refused);
  }
  return new InteractiveReactor(call, context_);
}

grpc::ServerWriteReactor<v1::SolvedFrame>* SolveServiceImpl::Solve(grpc::CallbackServerContext* call,
                                                                   const v1::SolveRequest* request) {
  if (auto refused = Refused(call, context_, "Solve", Access::kRead)) {
    return new Refusal<grpc::ServerWriteReactor<v1::SolvedFrame>>(*refused);
  }
  return new SolveReactor(call, context_, request);
}

}  // namespace springblend::server
