// The gRPC services: thin handlers that validate and convert, hand the work to the solver pool, and stream
// results back. No solve ever runs on a gRPC thread.
#pragma once

#include <atomic>
#include <chrono>
#include <limits>
#include <memory>
#include <string>

#include "character_store.h"
#include "convert.h"
#include "memory_budget.h"
#include "metrics.h"
#include "security.h"
#include "solver_pool.h"
#include "watchdog.h"
#include "springblend/v1/springblend.grpc.pb.h"

namespace springblend::server {

// The end of a shutdown's drain (Server::Shutdown sets it): past it the server stops waiting for in-flight
// work, and a rig build (an upload's, or a rebuild from the cache directory) stops too rather than hold the
// shutdown for minutes. Never passed before a shutdown.
class DrainDeadline {
 public:
  void Set(std::chrono::steady_clock::time_point end) {
    end_.store(end.time_since_epoch().count(), std::memory_order_relaxed);
  }
  bool Passed() const {
    return std::chrono::steady_clock::now().time_since_epoch().count() >= end_.load(std::memory_order_relaxed);
  }

 private:
  std::atomic<std::chrono::steady_clock::rep> end_{std::numeric_limits<std::chrono::steady_clock::rep>::max()};
};

struct ServiceContext {
  CharacterStore& store;
  SolverPool& pool;           // solves and builds: Solve, Interactive, UploadCharacter
  SolverPool& metadata_pool;  // GetCharacter, ListCharacters, DeleteCharacter: never behind a solve
  Limits limits;
  std::string replica_name;  // reported in every frame's served_by
  Metrics& metrics;
  const TokenAuthenticator& auth;  // checked first by every handler; without tokens every call is allowed
  MemoryBudget& memory;            // uploads in progress and open streams (--request-memory-mb)
  Watchdog& watchdog;              // stalled streams and idle sessions (--stall-seconds, --idle-seconds)
  const DrainDeadline& drain;      // builds stop once a shutdown's drain is over
};

// Every method is registered raw (grpc::ByteBuffer in and out) so that bytes which do not parse as the request
// message get INVALID_ARGUMENT with a message from us, instead of gRPC's bare UNIMPLEMENTED (unary, Solve) or
// a silently ended stream (Interactive). Handlers parse first, then work on the typed messages.
using CharacterServiceBase = v1::CharacterService::WithRawCallbackMethod_UploadCharacter<
    v1::CharacterService::WithRawCallbackMethod_GetCharacter<v1::CharacterService::WithRawCallbackMethod_ListCharacters<
        v1::CharacterService::WithRawCallbackMethod_DeleteCharacter<v1::CharacterService::Service>>>>;
using SolveServiceBase = v1::SolveService::WithRawCallbackMethod_Solve<
    v1::SolveService::WithRawCallbackMethod_Interactive<v1::SolveService::Service>>;

class CharacterServiceImpl final : public CharacterServiceBase {
 public:
  explicit CharacterServiceImpl(ServiceContext& context) : context_(context) {}
  grpc::ServerReadReactor<grpc::ByteBuffer>* UploadCharacter(grpc::CallbackServerContext* call,
                                                             grpc::ByteBuffer* response) override;
  grpc::ServerUnaryReactor* GetCharacter(grpc::CallbackServerContext* call, const grpc::ByteBuffer* request,
                                         grpc::ByteBuffer* response) override;
  grpc::ServerUnaryReactor* ListCharacters(grpc::CallbackServerContext* call, const grpc::ByteBuffer* request,
                                           grpc::ByteBuffer* response) override;
  grpc::ServerUnaryReactor* DeleteCharacter(grpc::CallbackServerContext* call, const grpc::ByteBuffer* request,
                                            grpc::ByteBuffer* response) override;

 private:
  ServiceContext& context_;
};

class SolveServiceImpl final : public SolveServiceBase {
 public:
  explicit SolveServiceImpl(ServiceContext& context) : context_(context) {}
  grpc::ServerWriteReactor<grpc::ByteBuffer>* Solve(grpc::CallbackServerContext* call,
                                                    const grpc::ByteBuffer* request) override;
  grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>* Interactive(grpc::CallbackServerContext* call) override;

 private:
  ServiceContext& context_;
};

}  // namespace springblend::server
