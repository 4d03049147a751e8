// Prometheus metrics of the server in the text exposition format, on a small HTTP endpoint of its own.
// Ours, not prometheus-cpp (Debian 12's prometheus-cpp-dev 1.0.1): its pull server is civetweb, which crashed on
// the first request here (Debian's build adds struct fields its header hides), and a few dozen families do not
// need its registry. The endpoint is a single-threaded HTTP/1.0 responder: GET /metrics, a one-line pointer to
// it at GET /, 404 for the rest, one scrape at a time. Counters and histograms are lock-free (the per-method
// ones behind one mutex); cache, pool and process figures are read when scraped.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>


namespace springblend::server {

using MetricsClock = std::chrono::steady_clock;

// Upper bounds of histogram buckets, in seconds.
// A frame of a small rig takes milliseconds, of the face seconds; a solve job may wait behind a bake.
inline const std::vector<double> kFrameBuckets = {0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5,
                                                  1.0,   2.5,    5.0,   10.0, 30.0,  60.0, 120.0, 300.0};
// Calls: a Get in milliseconds, an upload (its build) or a bake for minutes.
inline const std::vector<double> kCallBuckets = {0.005, 0.01, 0.025, 0.05, 0.1,   0.25,  0.5,   1.0,  2.5,
                                                 5.0,   10.0, 30.0,  60.0, 120.0, 300.0, 600.0, 1800.0};
// Rig builds: a cylinder in a second, the face's target paths for minutes.
inline const std::vector<double> kBuildBuckets = {0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
                                                  60.0, 120.0, 300.0, 600.0, 1200.0, 1800.0, 3600.0};

class Histogram {
 public:
  explicit Histogram(std::vector<double> bounds);
  void Observe(double value);
  // HELP, TYPE and the one series.
  std::string Render(const std::string& name, const std::string& help) const;
  // The series' bucket, sum and count lines; `labels` (`grpc_method="Solve"`) go before `le`.
  std::string RenderSeries(const std::string& name, const std::string& labels) const;

 private:
  const std::vector<double> bounds_;
  std::unique_ptr<std::atomic<std::uint64_t>[]> buckets_;  // bounds_.size() + 1, the last for +Inf
  std::atomic<std::uint64_t> count_{0};
  std::atomic<double> sum_{0.0};
};

class Metrics {
 public:
  Metrics();
  // The call's end. method: Solve, Interactive, UploadCharacter, ...; code: the gRPC status name (OK,
  // NOT_FOUND, ...); `started`: when the call came in (a refusal before any work: now, by default).
  void CountRequest(const std::string& method, const std::string& code,
                    MetricsClock::time_point started = MetricsClock::now());
  // A rig build's time (Rig summary's precompute), as the upload that waited for it saw it.
  void ObserveBuild(double seconds) { build_seconds_.Observe(seconds); }
  // How long a job waited in the solve pool's queue before a worker took it.
  void ObserveQueueWait(double seconds) { queue_wait_seconds_.Observe(seconds); }
  // Open Solve streams and Interactive sessions: +1 when one starts, -1 when it is gone (OpenCall does both).
  std::atomic<std::int64_t> solve_streams{0}, interactive_sessions{0};
  // Uploads whose routing header (x-springblend-character) was not the id the server gave the character: a
  // client that computes ids differently, so a balancer may build the character on another replica than the
  // one its solves go to.
  std::atomic<std::uint64_t> upload_routing_mismatches{0};

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
  std::map<std::pair<std::string, std::string>, std::uint64_t> requests_;  // by method and code
  std::map<std::string, std::unique_ptr<Histogram>> handling_seconds_;     // by method
  std::atomic<std::uint64_t> frames_{0}, unconverged_frames_{0}, newton_iterations_{0}, colliders_{0};
  std::atomic<std::int64_t> solvers_{0}, solver_bytes_{0};
  Histogram solve_seconds_{kFrameBuckets};
  Histogram build_seconds_{kBuildBuckets};
  Histogram queue_wait_seconds_{kFrameBuckets};
  const double start_time_seconds_;  // the process's, since the epoch
};

// A call counted in an open-calls gauge for the life of its reactor.
class OpenCall {
 public:
  explicit OpenCall(std::atomic<std::int64_t>& gauge) : gauge_(gauge) { gauge_.fetch_add(1); }
  ~OpenCall() { gauge_.fetch_sub(1); }
  OpenCall(const OpenCall&) = delete;
  OpenCall& operator=(const OpenCall&) = delete;

 private:
  std::atomic<std::int64_t>& gauge_;
};

// Resident memory, open descriptors, threads and CPU time of this process (Linux /proc), named as
// Prometheus' client libraries name them.
std::string ProcessMetrics(double start_time_seconds);

// Serves GET /metrics (and a pointer to it at GET /) on `listen` ("127.0.0.1:9100"; port 0 picks one). Stops
// in the destructor.
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
