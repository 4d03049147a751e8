#include "service.h"

#include <spdlog/spdlog.h>

#include <chrono>
#include <condition_variable>
#include <mutex>

#include "springblend/error.h"
#include "status.h"

namespace springblend::server {
namespace {

const grpc::Status kQueueFull(grpc::StatusCode::RESOURCE_EXHAUSTED,
                              "the server's solve queue is full; retry later or add replicas");

// Runs `work` on the pool and finishes the unary call with its status; refuses at once when the queue is full.
template <typename Work>
grpc::ServerUnaryReactor* OnPool(grpc::CallbackServerContext* call, SolverPool& pool, Work work) {
  grpc::ServerUnaryReactor* reactor = call->DefaultReactor();
  const bool queued = pool.TrySubmit([reactor, work = std::move(work)]() mutable {
    grpc::Status status;
    try {
      status = work();
    } catch (const std::exception& e) {
      status = ToStatus(e);
    }
    reactor->Finish(status);
  });
  if (!queued) reactor->Finish(kQueueFull);
  return reactor;
}

grpc::Status NotFound(const std::string& id) {
  return {grpc::StatusCode::NOT_FOUND,
          "no character with id '" + id + "' on this server or in its cache directory; upload it first"};
}

class UploadReactor final : public grpc::ServerReadReactor<v1::UploadChunk> {
 public:
  UploadReactor(grpc::CallbackServerContext* call, ServiceContext& context, v1::Character* response)
      : call_(call), context_(context), response_(response), assembler_(context.limits) {
    StartRead(&chunk_);
  }

  void OnReadDone(bool ok) override {
    if (!ok) {
      if (call_->IsCancelled()) {
        Finish({grpc::StatusCode::CANCELLED, "the upload was cancelled"});
        return;
      }
      Complete();
      return;
    }
    try {
      assembler_.Add(chunk_);
    } catch (const std::exception& e) {
      const grpc::Status status = ToStatus(e);
      Finish(assembler_.over_limit() ? grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED, status.error_message())
                                     : status);
      return;
    }
    StartRead(&chunk_);
  }
  void OnDone() override { delete this; }

 private:
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
      Finish(status);
    });
    if (!queued) Finish(kQueueFull);
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
    if (!context_.pool.TrySubmit([this] { Run(); })) Finish(kQueueFull);
  }

  void OnWriteDone(bool ok) override {
    std::lock_guard lock(mutex_);
    writing_ = false;
    if (!ok) cancelled_ = true;
    wake_.notify_all();
  }
  void OnCancel() override {
    std::lock_guard lock(mutex_);
    cancelled_ = true;
    wake_.notify_all();
  }
  void OnDone() override { delete this; }

 private:
  // On a pool worker. Finish is the last thing it does: OnDone (and delete) may follow at once.
  void Run() {
    const auto entry = context_.store.Get(request_->character_id());
    if (!entry) {
      Finish(NotFound(request_->character_id()));
      return;
    }
    SolveJob job;
    try {
      job = ToSolveJob(*request_, *entry->rig, context_.limits);
    } catch (const std::exception& e) {
      Finish(ToStatus(e));
      return;
    }
    try {
      Solver solver(entry->rig, job.options);
      solver.SetColliders(std::move(job.colliders));
      Points positions;
      for (size_t i = 0; i < job.frames.size(); ++i) {
        if (Stopped()) {
          Finish(Expired() ? grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED, fmt::format("deadline passed after {} of {} frames", i, job.frames.size()))
                           : grpc::Status(grpc::StatusCode::CANCELLED, "the client cancelled the stream"));
          return;
        }
        const SolveSummary summary = solver.Solve(job.frames[i], &positions);
        frame_ = ToProto(static_cast<int>(i), positions, entry->rig->rest().faces, summary, job.with_normals,
                         context_.replica_name);
        {
          std::unique_lock lock(mutex_);
          writing_ = true;
        }
        StartWrite(&frame_);
        std::unique_lock lock(mutex_);
        wake_.wait(lock, [this] { return !writing_ || cancelled_; });
        if (writing_) {
          // Cancelled mid-write: gRPC still completes the write (OnWriteDone) before OnDone; wait for it.
          wake_.wait(lock, [this] { return !writing_; });
        }
      }
    } catch (const std::exception& e) {
      Finish(ToStatus(e));
      return;
    }
    Finish(grpc::Status::OK);
  }

  bool Expired() const { return std::chrono::system_clock::now() > call_->deadline(); }
  bool Stopped() {
    std::lock_guard lock(mutex_);
    return cancelled_ || Expired();
  }

  grpc::CallbackServerContext* call_;
  ServiceContext& context_;
  const v1::SolveRequest* request_;
  v1::SolvedFrame frame_;
  std::mutex mutex_;
  std::condition_variable wake_;
  bool writing_ = false;
  bool cancelled_ = false;
};

}  // namespace

grpc::ServerReadReactor<v1::UploadChunk>* CharacterServiceImpl::UploadCharacter(grpc::CallbackServerContext* call,
                                                                                v1::Character* response) {
  return new UploadReactor(call, context_, response);
}

grpc::ServerUnaryReactor* CharacterServiceImpl::GetCharacter(grpc::CallbackServerContext* call,
                                                             const v1::GetCharacterRequest* request,
                                                             v1::Character* response) {
  return OnPool(call, context_.pool, [this, request, response]() -> grpc::Status {
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
  return OnPool(call, context_.pool, [this, response]() -> grpc::Status {
    for (const auto& entry : context_.store.List()) *response->add_characters() = ToProto(*entry, true);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* CharacterServiceImpl::DeleteCharacter(grpc::CallbackServerContext* call,
                                                                const v1::DeleteCharacterRequest* request,
                                                                v1::DeleteCharacterResponse*) {
  return OnPool(call, context_.pool, [this, request]() -> grpc::Status {
    if (!context_.store.Delete(request->id())) return NotFound(request->id());
    spdlog::info("deleted {}", request->id().substr(0, 12));
    return grpc::Status::OK;
  });
}

grpc::ServerWriteReactor<v1::SolvedFrame>* SolveServiceImpl::Solve(grpc::CallbackServerContext* call,
                                                                   const v1::SolveRequest* request) {
  return new SolveReactor(call, context_, request);
}

}  // namespace springblend::server
