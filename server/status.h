// The one place that maps springblend's errors onto gRPC status codes.
#pragma once

#include <grpcpp/support/status.h>

#include <exception>

namespace springblend::server {

// springblend::Error: kInvalidInput -> INVALID_ARGUMENT, kNotFound -> NOT_FOUND, kNumerical -> INTERNAL
// (with the solver's words), kInternal -> INTERNAL; anything else -> INTERNAL. The message is kept: it
// names the field, vertex or face at fault.
grpc::Status ToStatus(const std::exception& error);

}  // namespace springblend::server
