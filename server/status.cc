#include "status.h"

#include <grpc/grpc.h>

#include "springblend/error.h"

namespace springblend::server {

grpc::Status ToStatus(const std::exception& error) {
  if (dynamic_cast<const LimitError*>(&error)) return {grpc::StatusCode::RESOURCE_EXHAUSTED, error.what()};
  if (dynamic_cast<const CancelledError*>(&error)) return {grpc::StatusCode::CANCELLED, error.what()};
  if (const auto* e = dynamic_cast<const Error*>(&error)) {
    switch (e->code()) {
      case ErrorCode::kInvalidInput: return {grpc::StatusCode::INVALID_ARGUMENT, e->what()};
      case ErrorCode::kNotFound: return {grpc::StatusCode::NOT_FOUND, e->what()};
      case ErrorCode::kNumerical: return {grpc::StatusCode::INTERNAL, std::string("solver: ") + e->what()};
      case ErrorCode::kCancelled: return {grpc::StatusCode::CANCELLED, e->what()};
      case ErrorCode::kInternal: break;
    }
  }
  return {grpc::StatusCode::INTERNAL, std::string("internal error: ") + error.what()};
}

grpc::Status QueueFull() {
  return {grpc::StatusCode::RESOURCE_EXHAUSTED, "the server's solve queue is full; retry later or add replicas"};
}

grpc::Status ShuttingDown() { return {grpc::StatusCode::UNAVAILABLE, "the server is shutting down"}; }

grpc::Status NotFound(const std::string& id) {
  return {grpc::StatusCode::NOT_FOUND,
          "no character with id '" + id + "' on this server or in its cache directory; upload it first"};
}

grpc::Status Unparseable(const std::string& message) {
  return {grpc::StatusCode::INVALID_ARGUMENT, "the request bytes could not be parsed as a springblend.v1." + message +
                                                  " message (a client built from another proto, or corrupted bytes)"};
}

grpc::Status BadMessage(const std::string& what) { return {grpc::StatusCode::INVALID_ARGUMENT, what}; }

grpc::Status Cancelled(const std::string& why) { return {grpc::StatusCode::CANCELLED, why}; }

grpc::Status DeadlineExceeded(const std::string& what) { return {grpc::StatusCode::DEADLINE_EXCEEDED, what}; }

void CancelCall(grpc::ServerContextBase* call, const grpc::Status& status) {
  // What TryCancel does (no interceptor of ours watches cancellations), with our status and message.
  grpc_call_cancel_with_status(call->c_call(), static_cast<grpc_status_code>(status.error_code()),
                               status.error_message().c_str(), nullptr);
}

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
    case grpc::StatusCode::UNAVAILABLE: return "UNAVAILABLE";
    case grpc::StatusCode::INTERNAL: return "INTERNAL";
    default: return "OTHER";
  }
}

grpc::Status ToStatus(const AuthVerdict& verdict) {
  switch (verdict.kind) {
    case AuthVerdict::Kind::kAllowed: return grpc::Status::OK;
    case AuthVerdict::Kind::kMissing:
    case AuthVerdict::Kind::kUnknown: return {grpc::StatusCode::UNAUTHENTICATED, verdict.message};
    case AuthVerdict::Kind::kForbidden: return {grpc::StatusCode::PERMISSION_DENIED, verdict.message};
  }
  return {grpc::StatusCode::INTERNAL, "internal error: unknown authentication verdict"};
}

}  // namespace springblend::server
