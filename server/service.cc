// The handlers: each checks the token, parses, and hands the call to its kind (calls.h) or, for the unary
// metadata calls, to the metadata pool.
#include "service.h"

#include <spdlog/spdlog.h>

#include "call_support.h"
#include "calls.h"
#include "springblend/error.h"

namespace springblend::server {

grpc::ServerReadReactor<grpc::ByteBuffer>* CharacterServiceImpl::UploadCharacter(grpc::CallbackServerContext* call,
                                                                                 grpc::ByteBuffer* response) {
  if (auto refused = Refused(call, context_, "UploadCharacter", Access::kWrite)) {
    return new Refusal<grpc::ServerReadReactor<grpc::ByteBuffer>>(*refused);
  }
  return NewUploadCall(call, context_, response);
}

grpc::ServerUnaryReactor* CharacterServiceImpl::GetCharacter(grpc::CallbackServerContext* call,
                                                             const grpc::ByteBuffer* in, grpc::ByteBuffer* out) {
  return OnPoolDeferred<v1::GetCharacterRequest, v1::Character>(
      call, context_, "GetCharacter", Access::kRead, in, out,
      [this, call](const v1::GetCharacterRequest& request, v1::Character* response, const auto& done) {
        CheckId(request.id(), "id");
        const bool with_faces = request.with_faces();
        const auto answer = [this, call, response, with_faces, id = request.id()](
                                const std::shared_ptr<const CharacterStore::Entry>& entry, std::exception_ptr error) {
          if (error) return BuildStatus(error, call, context_);
          if (!entry) return NotFound(id);
          *response = ToProto(*entry, true);
          response->clear_cache_hit();
          if (with_faces) {
            const Faces& faces = entry->rig->rest().faces;
            response->set_faces(reinterpret_cast<const char*>(faces.data()), sizeof(int) * static_cast<size_t>(faces.size()));
          }
          return grpc::Status::OK;
        };
        CharacterStore::Found found = context_.store.Find(request.id(), !request.no_wait(), BuildWants(call, context_));
        if (!found.building || request.no_wait()) {
          if (found.building) {
            *response = ToProto(*found.building);
          } else if (found.stored) {
            response->set_id(request.id());
            response->set_state(v1::CHARACTER_STATE_STORED);
          } else {
            done(answer(found.entry, nullptr));
            return;
          }
          done(grpc::Status::OK);
          return;
        }
        // Waits for the build, holding no worker; the waiter goes with the callback, after it ran.
        auto waiter = std::make_shared<CharacterStore::Waiter>(std::move(found.waiter));
        found.building->OnDone([answer, done, waiter](const std::shared_ptr<const CharacterStore::Entry>& entry,
                                                      std::exception_ptr error) { done(answer(entry, error)); });
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
          } else if (listed.building) {
            *c = ToProto(*listed.building);
          } else {  // in the cache directory, not built yet: GetCharacter builds it
            c->set_id(listed.id);
            c->set_name(listed.name);
            c->set_state(v1::CHARACTER_STATE_STORED);
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
  return NewInteractiveCall(call, context_);
}

grpc::ServerWriteReactor<grpc::ByteBuffer>* SolveServiceImpl::Solve(grpc::CallbackServerContext* call,
                                                                    const grpc::ByteBuffer* in) {
  using Refuse = Refusal<grpc::ServerWriteReactor<grpc::ByteBuffer>>;
  Received(*in);
  if (auto refused = Refused(call, context_, "Solve", Access::kRead)) return new Refuse(*refused);
  // The bytes gRPC received are counted until parsed (a request of pins parses to several times its size).
  Reservation received(&context_.memory);
  try {
    received.Grow(static_cast<std::int64_t>(in->Length()));
  } catch (const std::exception& e) {
    return new Refuse(AnsweredAtOnce(call, context_, "Solve", ToStatus(e)));
  }
  v1::SolveRequest request;
  if (!Parse(*in, &request)) return new Refuse(AnsweredAtOnce(call, context_, "Solve", Unparseable("SolveRequest")));
  // gRPC keeps the request's bytes for the whole call; parsed, they are not needed (the buffer is the call's,
  // not const, and is only destroyed after this).
  const_cast<grpc::ByteBuffer*>(in)->Clear();
  return NewSolveCall(call, context_, std::move(request), received);
}

}  // namespace springblend::server
