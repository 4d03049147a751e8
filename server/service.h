// The gRPC services: thin handlers that validate and convert, hand the work to the solver pool, and stream
// results back. No solve ever runs on a gRPC thread.
#pragma once

#include <memory>
#include <string>

#include "character_store.h"
#include "convert.h"
#include "metrics.h"
#include "security.h"
#include "solver_pool.h"
#include "springblend/v1/springblend.grpc.pb.h"

namespace springblend::server {

struct ServiceContext {
  CharacterStore& store;
  SolverPool& pool;
  Limits limits;
  std::string replica_name;  // reported in every frame's served_by
  Metrics& metrics;
  const TokenAuthenticator& auth;  // checked first by every handler; without tokens every call is allowed
};

class CharacterServiceImpl final : public v1::CharacterService::CallbackService {
 public:
  explicit CharacterServiceImpl(ServiceContext& context) : context_(context) {}
  grpc::ServerReadReactor<v1::UploadChunk>* UploadCharacter(grpc::CallbackServerContext* call,
                                                            v1::Character* response) override;
  grpc::ServerUnaryReactor* GetCharacter(grpc::CallbackServerContext* call, const v1::GetCharacterRequest* request,
                                         v1::Character* response) override;
  grpc::ServerUnaryReactor* ListCharacters(grpc::CallbackServerContext* call, const v1::ListCharactersRequest* request,
                                           v1::ListCharactersResponse* response) override;
  grpc::ServerUnaryReactor* DeleteCharacter(grpc::CallbackServerContext* call,
                                            const v1::DeleteCharacterRequest* request,
                                            v1::DeleteCharacterResponse* response) override;

 private:
  ServiceContext& context_;
};

class SolveServiceImpl final : public v1::SolveService::CallbackService {
 public:
  explicit SolveServiceImpl(ServiceContext& context) : context_(context) {}
  grpc::ServerWriteReactor<v1::SolvedFrame>* Solve(grpc::CallbackServerContext* call,
                                                   const v1::SolveRequest* request) override;
  grpc::ServerBidiReactor<v1::InteractiveRequest, v1::SolvedFrame>* Interactive(
      grpc::CallbackServerContext* call) override;

 private:
  ServiceContext& context_;
};

}  // namespace springblend::server
