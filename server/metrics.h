// Prometheus metrics of the server in the text exposition format, on a small HTTP endpoint of its own.
// prometheus-cpp is not in Debian 12, and Debian's civetweb crashed on the first request here (its build
// adds struct fields its header hides), so the endpoint is a single-threaded HTTP/1.0 responder: it only ever
// answers GET /metrics, one scrape at a time. Counters and histograms are lock-free; cache and pool figures
// are read when scraped.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <functional>
#include <map>
#include <mutex>
#include <string>
#include <thread>


namespace springblend::server {

class Histogram {
 public:
  static constexpr std::array<double, 12> kBounds = {0.001, 0.0025, 0.005, 0.01, 0.025, 0.05,
                                                     0.1,   0.25,   0.5,   1.0,  2.5,   10.0};
  void Observe(double value);
  std::string Render(const std::string& name, const std::string& help, double scale = 1.0) const;

 private:
  std::array<std::atomic<std::uint64_t>, kBounds.size() + 1> buckets_{};
  std::atomic<std::uint64_t> count_{0};
  std::atomic<double> sum_{0.0};
};

class Metrics {
 public:
  // method: Solve, Interactive, UploadCharacter, ...; code: the gRPC status name (OK, NOT_FOUND, ...).
  void CountRequest(const std::string& method, const std::string& code);
  void CountFrame(double solve_seconds, int newton_iterations, bool converged);
  // Colliders turned into solver obstacles (a mesh collider: parsed or copied, checked, its AABB tree built).
  // A stream converts its colliders once, not per frame.
  void CountColliders(size_t converted);
  // Solvers held by open Solve streams and Interactive sessions, and the memory counted for them
  // (Solver::BytesFor; part of the request memory): +1 and its bytes when one is made, -1 when it goes.
  void HoldSolvers(int solvers, std::int64_t bytes);

  // Everything, in the exposition format; `extra` appends gauges read at scrape time.
  std::string Render(const std::function<std::string()>& extra) const;

 private:
  mutable std::mutex mutex_;
  std::map<std::pair<std::string, std::string>, std::uint64_t> requests_;
  std::atomic<std::uint64_t> frames_{0}, unconverged_frames_{0}, newton_iterations_{0}, colliders_{0};
  std::atomic<std::int64_t> solvers_{0}, solver_bytes_{0};
  Histogram solve_seconds_;
};

// Serves GET /metrics on `listen` ("127.0.0.1:9100"; port 0 picks one). Stops in the destructor.
class MetricsEndpoint {
 public:
  MetricsEndpoint(const std::string& listen, std::function<std::string()> render);
  ~MetricsEndpoint();
  int port() const { return port_; }

 private:
  void Serve();
  std::function<std::string()> render_;
  int socket_ = -1;
  int port_ = 0;
  std::atomic<bool> stopping_{false};
  std::thread thread_;
};

}  // namespace springblend::server
