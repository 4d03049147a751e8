#include <spdlog/spdlog.h>

#include <memory>
#include <mutex>
#include <optional>

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
    info_ = BeginCall(call, "UploadCharacter");
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
    EndCall(context_.metrics, info_, status);
    Finish(status);
  }
  // On the metadata pool: the pieces checked and assembled, then the build started on the build pool (or the
  // character found). The call waits for its build without holding a thread; the id goes out at once as
  // initial metadata (kCharacterIdHeader), so a client can follow the build with GetCharacter(no_wait).
  void Complete() {
    const bool queued = context_.metadata_pool.TrySubmit([this] {
      CharacterStore::Found found;
      try {
        found = context_.store.Start(assembler_.Finish(), BuildWants(call_, context_));
      } catch (const std::exception& e) {
        Built(nullptr, std::current_exception(), true);
        return;
      }
      if (found.building) {
        CheckRouting(found.building->id());
      } else if (found.entry) {
        CheckRouting(found.entry->id);
      }
      if (!found.building) {
        Built(found.entry, nullptr, true);
        return;
      }
      {
        std::lock_guard lock(mutex_);
        waiter_ = std::move(found.waiter);
        sending_metadata_ = true;
        info_.character = found.building->id();
      }
      spdlog::info("upload {} '{}': {} (request_id={})", found.building->id().substr(0, 12),
                   Printable(found.building->name()),
                   found.joined  ? "joins the build already in flight"
                   : found.known ? "rebuilding from the cache directory"
                                 : "building",
                   info_.request_id);
      joined_ = found.joined;
      call_->AddInitialMetadata(kCharacterIdHeader, found.building->id());
      StartSendInitialMetadata();
      const bool known = found.known;
      found.building->OnDone([this, known](const std::shared_ptr<const CharacterStore::Entry>& entry,
                                           std::exception_ptr error) {
        if (entry) context_.metrics.ObserveBuild(entry->rig->summary().precompute_ms / 1000.0);
        Built(entry, error, known);
      });
    });
    if (!queued) Done(kQueueFull);
  }
  // A client that sends the routing header computed the id before the upload, so that a balancer hashing the
  // header sends the upload to the replica its solves will reach; a header that is not the id says that
  // client computes it differently (logged and counted, the upload itself goes on).
  void CheckRouting(const std::string& id) {
    const auto& metadata = call_->client_metadata();
    const auto header = metadata.find(kRoutingHeader);
    if (header == metadata.end()) return;
    const std::string_view sent(header->second.data(), header->second.size());
    if (sent == id) return;
    context_.metrics.upload_routing_mismatches.fetch_add(1, std::memory_order_relaxed);
    spdlog::warn("upload {}: its {} header ({}) is not its id: the client computes ids differently, so a balancer "
                 "may build it on another replica than the one its solves reach",
                 id.substr(0, 12), kRoutingHeader, Printable(sent, 80));
  }
  void OnSendInitialMetadataDone(bool) override {
    std::unique_lock lock(mutex_);
    sending_metadata_ = false;
    FinishIfDue(lock);
  }
  // The build's end (on its thread, or on the pool when there was none to wait for).
  void Built(const std::shared_ptr<const CharacterStore::Entry>& entry, std::exception_ptr error, bool known) {
    grpc::Status status;
    if (call_->IsCancelled() || CallExpired(*call_)) {
      // Its client gave up while it was built: logged and counted as what that client saw, not as an OK.
      status = CallExpired(*call_) ? DeadlineExceeded("the deadline passed while the character was being built")
                                   : Cancelled("the call was cancelled while the character was being built");
      spdlog::info("upload {}: {} ({}; request_id={})", entry ? entry->id.substr(0, 12) : std::string("refused"),
                   status.error_message(), entry ? "the character is kept" : "the build ended without it",
                   info_.request_id);
    } else if (error) {
      status = BuildStatus(error, call_, context_);
      spdlog::warn("upload refused: {} (request_id={})", Printable(status.error_message(), 400), info_.request_id);
    } else if (!entry) {
      status = ToStatus(Error(ErrorCode::kInternal, "the character's cache file went missing while it was read; upload "
                                                    "it again"));
    } else {
      *response_ = Serialize(ToProto(*entry, known));
      spdlog::info("upload {} '{}': {} ({} vertices, {} springs, {:.0f} ms; request_id={})", entry->id.substr(0, 12),
                   Printable(entry->name), joined_ ? "built (joined the build already in flight)" : known ? "cache hit" : "built",
                   entry->rig->num_vertices(),
                   entry->rig->num_springs(), entry->rig->summary().precompute_ms, info_.request_id);
    }
    std::unique_lock lock(mutex_);
    if (entry) info_.character = entry->id;
    waiter_.reset();
    due_ = status;
    FinishIfDue(lock);
  }
  // Finish once the build is over and the initial metadata (if any) is sent.
  void FinishIfDue(std::unique_lock<std::mutex>& lock) {
    if (!due_ || sending_metadata_) return;
    const grpc::Status status = *due_;
    due_.reset();
    lock.unlock();
    Done(status);
  }

  grpc::CallbackServerContext* call_;
  ServiceContext& context_;
  CallInfo info_;
  grpc::ByteBuffer* response_;
  std::shared_ptr<Watchdog::Handle> watch_;
  UploadAssembler assembler_;
  grpc::ByteBuffer bytes_;
  std::mutex mutex_;
  CharacterStore::Waiter waiter_;  // while the build runs
  bool sending_metadata_ = false;
  bool joined_ = false;  // waited for a build another call started
  std::optional<grpc::Status> due_;  // the build ended with it
};

}  // namespace

grpc::ServerReadReactor<grpc::ByteBuffer>* NewUploadCall(grpc::CallbackServerContext* call, ServiceContext& context,
                                                         grpc::ByteBuffer* response) {
  return new UploadReactor(call, context, response);
}

}  // namespace springblend::server
