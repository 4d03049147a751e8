// A load generator for a springblend server: many concurrent Solve streams against one character, bounded in
// requests and in time, for load tests and capacity planning. Loopback only: it refuses any other address, so
// nobody loads a shared farm by accident.
#pragma once

#include <chrono>
#include <map>
#include <string>
#include <vector>

#include "springblend/client.h"

namespace springblend {

struct LoadOptions {
  std::string character_id;       // an uploaded character
  std::vector<double> weights;    // the end of each request's sweep, one per target
  int streams = 8;                // concurrent clients, each with its own channel, one request at a time
  int frames_per_request = 4;     // frames in each Solve request (a sweep from the rest shape to `weights`)
  int max_requests = 1000;        // stop after this many requests in all
  std::chrono::milliseconds duration{std::chrono::seconds(60)};  // or after this long
};

struct LoadReport {
  int requests = 0;  // finished, OK or not
  int errors = 0;
  std::map<std::string, int> errors_by_code;  // status code name -> count
  std::string first_error;                     // its message
  long long frames = 0;
  double seconds = 0.0;
  // Request latency (send to last frame), milliseconds.
  double p50_ms = 0.0, p90_ms = 0.0, p99_ms = 0.0, max_ms = 0.0;

  double requests_per_second() const { return seconds > 0 ? requests / seconds : 0.0; }
  std::string Json() const;  // one line
};

// Runs the load and reports. Throws ClientError(INVALID_ARGUMENT) for a non-loopback address or bad options.
LoadReport RunLoad(const ClientOptions& client, const LoadOptions& options);

}  // namespace springblend
