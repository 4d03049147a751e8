// What every call kind shares: parsing raw requests, the token check, refusals, unary work on a pool, the
// solvers a stream holds in the memory budget, and the statuses of stopped work. The call kinds themselves
// live in upload_call.cc, solve_call.cc and interactive_call.cc; service.cc only dispatches to them.
#pragma once

#include <grpcpp/grpcpp.h>
#include <grpcpp/support/byte_buffer.h>
#include <grpcpp/support/proto_buffer_reader.h>
#include <fmt/format.h>

#include <chrono>
#include <cstdint>
#include <exception>
#include <optional>

#include "access_log.h"
#include "service.h"
#include "springblend/error.h"
#include "status.h"

namespace springblend::server {

inline const grpc::Status kQueueFull = QueueFull();

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

// A call answered before any work (a refusal): counted and logged like any other answer.
inline grpc::Status AnsweredAtOnce(grpc::CallbackServerContext* call, ServiceContext& context, const char* method,
                                   const grpc::Status& status) {
  EndCall(context.metrics, BeginCall(call, method), status);
  return status;
}

// The token check every handler makes before any work; a refusal is counted and logged like any other answer.
inline std::optional<grpc::Status> Refused(grpc::CallbackServerContext* call, ServiceContext& context, const char* method,
                                    Access needed) {
  const AuthVerdict verdict = context.auth.Check(*call, needed);
  if (verdict.allowed()) return std::nullopt;
  return AnsweredAtOnce(call, context, method, ToStatus(verdict));
}

// A streaming call refused before any work: it answers with the status and goes.
template <typename Reactor>
class Refusal final : public Reactor {
 public:
  explicit Refusal(const grpc::Status& status) { this->Finish(status); }
  void OnDone() override { delete this; }
};

// The largest request GetCharacter, ListCharacters and DeleteCharacter take: an id and a few flags. gRPC has one
// receive limit for every method (ServerOptions::max_receive_message_bytes), which Solve's and Interactive's
// requests need, and receives a unary request whole before any handler (or interceptor) runs; a larger one is
// refused with RESOURCE_EXHAUSTED before it is parsed, and its memory given back (ReturnFreeHeapSoon).
inline constexpr std::int64_t kMetadataRequestLimit = 1 << 20;

// A request as gRPC received it, before the token is checked: a large one asks for the heap to be trimmed once
// its call has ended (its buffers freed), whatever the answer.
inline void Received(const grpc::ByteBuffer& request) {
  if (static_cast<std::int64_t>(request.Length()) >= kLargeRequestBytes) ReturnFreeHeapSoon();
}

// Parses the request, then runs `work(request, &response, done)` on the metadata pool; `done(status)` finishes
// the unary call, once, from any thread (now, or later: a call that waits for a build holds no worker).
// Refuses at once when the token does not allow the call, the bytes do not parse, or the queue is full.
template <typename Request, typename Response, typename Work>
grpc::ServerUnaryReactor* OnPoolDeferred(grpc::CallbackServerContext* call, ServiceContext& context,
                                         const char* method, Access needed, const grpc::ByteBuffer* in,
                                         grpc::ByteBuffer* out, Work work) {
  SolverPool& pool = context.metadata_pool;
  grpc::ServerUnaryReactor* reactor = call->DefaultReactor();
  Metrics& metrics = context.metrics;
  Received(*in);
  if (auto refused = Refused(call, context, method, needed)) {
    reactor->Finish(*refused);
    return reactor;
  }
  CallInfo info = BeginCall(call, method);
  if (const auto bytes = static_cast<std::int64_t>(in->Length()); bytes > kMetadataRequestLimit) {
    const grpc::Status status = ToStatus(LimitError(fmt::format(
        "the {} request is {} bytes, over this method's limit of {} bytes (an id and a few flags)", method, bytes,
        kMetadataRequestLimit)));
    EndCall(metrics, info, status);
    reactor->Finish(status);
    return reactor;
  }
  auto request = std::make_shared<Request>();
  if (!Parse(*in, request.get())) {
    const grpc::Status status = Unparseable(Request::descriptor()->name());
    EndCall(metrics, info, status);
    reactor->Finish(status);
    return reactor;
  }
  if constexpr (requires { request->id(); }) info.character = request->id();
  const bool queued = pool.TrySubmit([reactor, &metrics, info, request, out, work = std::move(work)]() mutable {
    auto response = std::make_shared<Response>();
    const auto done = [reactor, &metrics, info, response, out](const grpc::Status& status) {
      if (status.ok()) *out = Serialize(*response);
      EndCall(metrics, info, status);
      reactor->Finish(status);
    };
    try {
      work(*request, response.get(), done);
    } catch (const std::exception& e) {
      done(ToStatus(e));
    }
  });
  if (!queued) {
    EndCall(metrics, info, kQueueFull);
    reactor->Finish(kQueueFull);
  }
  return reactor;
}

// OnPoolDeferred for work that answers before it returns: `work(request, &response)` gives the status.
template <typename Request, typename Response, typename Work>
grpc::ServerUnaryReactor* OnPool(grpc::CallbackServerContext* call, ServiceContext& context, const char* method,
                                 Access needed, const grpc::ByteBuffer* in, grpc::ByteBuffer* out, Work work) {
  return OnPoolDeferred<Request, Response>(
      call, context, method, needed, in, out,
      [work = std::move(work)](const Request& request, Response* response, const auto& done) mutable {
        done(work(request, response));
      });
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

inline grpc::Status StoppedStatus(const Watchdog::Handle& watch, const char* what) {
  if (const char* why = watch.expired()) return Cancelled(why);
  return Cancelled(what);
}

inline const grpc::Status kShuttingDown = ShuttingDown();

inline bool CallExpired(const grpc::CallbackServerContext& call) { return std::chrono::system_clock::now() > call.deadline(); }

// Whether a call still wants the build it waits for (an upload's, or a rebuild from the cache directory): not
// cancelled, within its deadline, and the shutdown's drain not over. A build goes on while one of its waiters
// wants it.
inline CharacterStore::Wants BuildWants(grpc::CallbackServerContext* call, const ServiceContext& context) {
  return [call, &context] { return !call->IsCancelled() && !CallExpired(*call) && !context.drain.Passed(); };
}

// The response metadata that carries an upload's character id as soon as the pieces are checked.
inline constexpr char kCharacterIdHeader[] = "springblend-character-id";
// The routing header clients send (the character's id, computed before an upload: docs/server.md#routing).
inline constexpr char kRoutingHeader[] = "x-springblend-character";

// The status of a build's error for a call that waited for it: a stopped build says why it stopped.
inline grpc::Status BuildStatus(const std::exception& error, grpc::CallbackServerContext* call, const ServiceContext& context) {
  const auto* e = dynamic_cast<const Error*>(&error);
  if (e == nullptr || e->code() != ErrorCode::kCancelled) return ToStatus(error);
  if (context.drain.Passed()) return kShuttingDown;
  if (CallExpired(*call)) return DeadlineExceeded("the deadline passed while the character was being built");
  return Cancelled("the call was cancelled while the character was being built");
}
// The same for a build's error as PendingBuild::OnDone passes it.
inline grpc::Status BuildStatus(std::exception_ptr error, grpc::CallbackServerContext* call,
                                const ServiceContext& context) {
  try {
    std::rethrow_exception(error);
  } catch (const std::exception& e) {
    return BuildStatus(e, call, context);
  } catch (...) {
    return ToStatus(Error(ErrorCode::kInternal, "the build failed with an unknown error"));
  }
}

// The status of a frame's (or preview's) error. A rig whose paths could not be read back from its cache file (cut
// short or failing under it: DataLossError) fails every frame the same way: it is dropped from the store, so the
// next upload or call that needs the character builds it anew, and the client is told so.
inline grpc::Status FrameStatus(const std::exception& error, const std::shared_ptr<const CharacterStore::Entry>& entry,
                                ServiceContext& context) {
  if (entry != nullptr && dynamic_cast<const DataLossError*>(&error) != nullptr) {
    context.store.Drop(entry, error.what());
    return ToStatus(DataLossError(std::string(error.what()) +
                                  "; the character was dropped from memory: retry (it is rebuilt from its cache file "
                                  "if that is whole) or upload it again"));
  }
  return ToStatus(error);
}

}  // namespace springblend::server
