// The one place that maps springblend's errors onto gRPC status codes.
#pragma once

#include <grpcpp/support/status.h>

#include <exception>
#include <stdexcept>
#include <string>

#include "security.h"

namespace springblend::server {

// A request over one of the server's limits (frames, upload size, the memory budget, the queue): the request may
// be fine, the server will not take it now. Maps to RESOURCE_EXHAUSTED.
class LimitError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Work stopped because its call was cancelled (or its deadline passed) part way. Maps to CANCELLED.
class CancelledError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// LimitError -> RESOURCE_EXHAUSTED, CancelledError -> CANCELLED. springblend::Error: kInvalidInput -> INVALID_ARGUMENT, kNotFound -> NOT_FOUND, kNumerical -> INTERNAL
// (with the solver's words), kInternal -> INTERNAL; anything else -> INTERNAL. The message is kept: it
// names the field, vertex or face at fault.
grpc::Status ToStatus(const std::exception& error);

// A refused token check: no token or an unknown one -> UNAUTHENTICATED; a known token whose role does not
// allow the call -> PERMISSION_DENIED.
grpc::Status ToStatus(const AuthVerdict& verdict);

}  // namespace springblend::server
