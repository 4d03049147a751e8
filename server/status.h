// The one place that maps springblend's errors onto gRPC status codes.
#pragma once

#include <grpcpp/support/status.h>

#include <exception>

#include "security.h"

namespace springblend::server {

// springblend::Error: kInvalidInput -> INVALID_ARGUMENT, kNotFound -> NOT_FOUND, kNumerical -> INTERNAL
// (with the solver's words), kInternal -> INTERNAL; anything else -> INTERNAL. The message is kept: it
// names the field, vertex or face at fault.
grpc::Status ToStatus(const std::exception& error);

// A refused token check: no token or an unknown one -> UNAUTHENTICATED; a known token whose role does not
// allow the call -> PERMISSION_DENIED.
grpc::Status ToStatus(const AuthVerdict& verdict);

}  // namespace springblend::server
