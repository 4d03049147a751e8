#include <spdlog/spdlog.h>

#include <memory>

#include "call_support.h"
#include "calls.h"
#include "springblend/error.h"

namespace springblend::server {
namespace {

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

}  // namespace

grpc::ServerReadReactor<grpc::ByteBuffer>* NewUploadCall(grpc::CallbackServerContext* call, ServiceContext& context,
                                                         grpc::ByteBuffer* response) {
  return new UploadReactor(call, context, response);
}

}  // namespace springblend::server
