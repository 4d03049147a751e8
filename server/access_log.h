// One access line per call, and the request id that ties a call's lines together.
//
// Every call gets a request id: the client's `x-request-id` metadata when it sends a usable one (1 to 128
// printable ASCII characters), else a new one (16 hex digits). The id goes back in the response's initial
// metadata (`x-request-id`) and in the call's access line: method, character (12 hex digits), frames, status
// name, milliseconds, peer and request id. Logs are text (spdlog's lines) or, with SetJsonLogs(true), one JSON
// object per line.
#pragma once

#include <grpcpp/grpcpp.h>

#include <cstdint>
#include <string>

#include "metrics.h"

namespace springblend::server {

inline constexpr char kRequestIdHeader[] = "x-request-id";

struct CallInfo {
  const char* method = "";
  std::string request_id;
  std::string peer;
  MetricsClock::time_point started = MetricsClock::now();
  std::string character;    // the character's id, when the call names one
  std::int64_t frames = -1;  // frames asked for (Solve) or sent (Interactive); -1: not a solving call
};

// At a call's start: its request id (added to the initial metadata, so call once per call, before anything is
// sent), peer and start time.
CallInfo BeginCall(grpc::CallbackServerContext* call, const char* method);

// At its end: counted in the metrics and logged as its access line.
void EndCall(Metrics& metrics, const CallInfo& call, const grpc::Status& status);

// Logs as JSON objects, one per line ({"time", "level", "message"}; access lines carry their fields as members),
// instead of text. Set once at start-up, before any call; installs the formatter on spdlog's default logger.
void SetJsonLogs(bool json);

}  // namespace springblend::server
