// The one place that maps springblend's errors onto gRPC status codes.
#pragma once

#include <grpcpp/server_context.h>
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

// The server's own answers, built here so that every status code is chosen in this file.
grpc::Status QueueFull();                               // RESOURCE_EXHAUSTED: the --queue is full
grpc::Status ShuttingDown();                            // UNAVAILABLE
grpc::Status NotFound(const std::string& id);           // NOT_FOUND: a valid id nobody uploaded
grpc::Status Unparseable(const std::string& message);   // INVALID_ARGUMENT: bytes that are not that message
grpc::Status BadMessage(const std::string& what);       // INVALID_ARGUMENT: a message out of place
grpc::Status Cancelled(const std::string& why);         // CANCELLED: by the client, or the watchdog
grpc::Status DeadlineExceeded(const std::string& what);  // DEADLINE_EXCEEDED
// Cancels a call with this status, which its client then sees (gRPC's TryCancel sends a bare "Cancelled on the
// server side"): for the watchdog's reasons and refusals made before a handler runs (reflection's token check).
void CancelCall(grpc::ServerContextBase* call, const grpc::Status& status);
// The code's name, for metrics labels.
const char* CodeName(grpc::StatusCode code);

// A refused token check: no token or an unknown one -> UNAUTHENTICATED; a known token whose role does not
// allow the call -> PERMISSION_DENIED.
grpc::Status ToStatus(const AuthVerdict& verdict);

}  // namespace springblend::server
