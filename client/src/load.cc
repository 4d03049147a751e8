#include "springblend/load.h"

#include <fmt/format.h>
#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <atomic>
#include <mutex>
#include <thread>

namespace springblend {
namespace {

bool IsLoopback(const std::string& address) {
  const std::string host = address.substr(0, address.rfind(':'));
  return host == "127.0.0.1" || host == "localhost" || host == "[::1]" || host.rfind("127.", 0) == 0;
}

double Percentile(const std::vector<double>& sorted, double p) {
  if (sorted.empty()) return 0.0;
  const size_t rank = static_cast<size_t>(p * static_cast<double>(sorted.size() - 1) + 0.5);
  return sorted[std::min(rank, sorted.size() - 1)];
}

}  // namespace

std::string LoadReport::Json() const {
  std::string codes;
  for (const auto& [code, count] : errors_by_code) codes += fmt::format("{}\"{}\": {}", codes.empty() ? "" : ", ", code, count);
  return fmt::format(
      "{{\"requests\": {}, \"errors\": {}, \"errors_by_code\": {{{}}}, \"frames\": {}, \"seconds\": {:.2f}, "
      "\"requests_per_second\": {:.2f}, \"latency_ms\": {{\"p50\": {:.1f}, \"p90\": {:.1f}, \"p99\": {:.1f}, "
      "\"max\": {:.1f}}}}}",
      requests, errors, codes, frames, seconds, requests_per_second(), p50_ms, p90_ms, p99_ms, max_ms);
}

LoadReport RunLoad(const ClientOptions& client, const LoadOptions& options) {
  if (!IsLoopback(client.address)) {
    throw ClientError(grpc::StatusCode::INVALID_ARGUMENT,
                      "the load generator only drives loopback servers (127.0.0.1, localhost, [::1]), not " +
                          client.address);
  }
  if (options.streams < 1 || options.frames_per_request < 1 || options.max_requests < 1 || options.weights.empty()) {
    throw ClientError(grpc::StatusCode::INVALID_ARGUMENT,
                      "load options: streams, frames_per_request and max_requests must be >= 1, weights non-empty");
  }
  v1::SolveRequest request;
  request.set_character_id(options.character_id);
  for (int i = 1; i <= options.frames_per_request; ++i) {
    v1::FrameRequest* frame = request.add_frames();
    for (double w : options.weights) frame->add_weights(w * i / options.frames_per_request);
  }

  using Clock = std::chrono::steady_clock;
  const auto start = Clock::now();
  const auto end = start + options.duration;
  std::atomic<int> issued{0};
  std::mutex mutex;
  LoadReport report;
  std::vector<double> latencies;
  std::vector<std::thread> threads;
  for (int s = 0; s < options.streams; ++s) {
    threads.emplace_back([&] {
      Client own(client);
      while (Clock::now() < end && issued.fetch_add(1) < options.max_requests) {
        const auto sent = Clock::now();
        int frames = 0;
        std::string error;
        int code = 0;
        try {
          frames = own.Solve(request, [](const v1::SolvedFrame&) {});
        } catch (const ClientError& e) {
          code = e.code();
          error = e.what();
        }
        const double ms = std::chrono::duration<double, std::milli>(Clock::now() - sent).count();
        std::lock_guard lock(mutex);
        ++report.requests;
        report.frames += frames;
        if (code != 0) {
          ++report.errors;
          ++report.errors_by_code[StatusName(code)];
          if (report.first_error.empty()) report.first_error = error;
        } else {
          latencies.push_back(ms);
        }
      }
    });
  }
  for (auto& t : threads) t.join();
  report.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  std::sort(latencies.begin(), latencies.end());
  report.p50_ms = Percentile(latencies, 0.50);
  report.p90_ms = Percentile(latencies, 0.90);
  report.p99_ms = Percentile(latencies, 0.99);
  report.max_ms = latencies.empty() ? 0.0 : latencies.back();
  return report;
}

}  // namespace springblend
