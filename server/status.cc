#include "status.h"

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
      case ErrorCode::kInternal: break;
    }
  }
  return {grpc::StatusCode::INTERNAL, std::string("internal error: ") + error.what()};
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
