#include "metrics.h"

#include <arpa/inet.h>
#include <dirent.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <charconv>
#include <chrono>
#include <cstring>
#include <fstream>
#include <sstream>
#include <vector>
#include <fmt/format.h>

#include "springblend/error.h"
#include "springblend/version.h"

namespace springblend::server {

Histogram::Histogram(std::vector<double> bounds)
    : bounds_(std::move(bounds)), buckets_(new std::atomic<std::uint64_t>[bounds_.size() + 1]) {
  for (size_t b = 0; b <= bounds_.size(); ++b) buckets_[b].store(0, std::memory_order_relaxed);
}

void Histogram::Observe(double value) {
  size_t bucket = 0;
  while (bucket < bounds_.size() && value > bounds_[bucket]) ++bucket;
  buckets_[bucket].fetch_add(1, std::memory_order_relaxed);
  count_.fetch_add(1, std::memory_order_relaxed);
  double sum = sum_.load(std::memory_order_relaxed);
  while (!sum_.compare_exchange_weak(sum, sum + value, std::memory_order_relaxed)) {
  }
}

std::string Histogram::Render(const std::string& name, const std::string& help) const {
  return fmt::format("# HELP {} {}\n# TYPE {} histogram\n", name, help, name) + RenderSeries(name, "");
}

std::string Histogram::RenderSeries(const std::string& name, const std::string& labels) const {
  const std::string before = labels.empty() ? "" : labels + ",";
  std::string out;
  std::uint64_t cumulative = 0;
  for (size_t b = 0; b < bounds_.size(); ++b) {
    cumulative += buckets_[b].load(std::memory_order_relaxed);
    out += fmt::format("{}_bucket{{{}le=\"{}\"}} {}\n", name, before, bounds_[b], cumulative);
  }
  cumulative += buckets_[bounds_.size()].load(std::memory_order_relaxed);
  const std::string braces = labels.empty() ? "" : "{" + labels + "}";
  out += fmt::format("{}_bucket{{{}le=\"+Inf\"}} {}\n{}_sum{} {}\n{}_count{} {}\n", name, before, cumulative, name,
                     braces, sum_.load(std::memory_order_relaxed), name, braces,
                     count_.load(std::memory_order_relaxed));
  return out;
}

namespace {

// The labels go-grpc-prometheus (and gRPC's OpenTelemetry plug-in, as grpc.method) gives a method.
std::string MethodLabels(const std::string& method) {
  const char* service = "springblend.v1.CharacterService";
  const char* type = "unary";
  if (method == "UploadCharacter") {
    type = "client_stream";
  } else if (method == "Solve") {
    service = "springblend.v1.SolveService";
    type = "server_stream";
  } else if (method == "Interactive") {
    service = "springblend.v1.SolveService";
    type = "bidi_stream";
  }
  return fmt::format("grpc_type=\"{}\",grpc_service=\"{}\",grpc_method=\"{}\"", type, service, method);
}

double ClockTicks() { return static_cast<double>(sysconf(_SC_CLK_TCK)); }

// /proc/self/stat's fields from the third (state) on: the command name before them may hold spaces.
std::vector<std::string> StatFields() {
  std::ifstream in("/proc/self/stat");
  std::string line;
  std::getline(in, line);
  std::vector<std::string> fields;
  const auto paren = line.rfind(')');
  if (paren == std::string::npos) return fields;
  std::istringstream rest(line.substr(paren + 1));
  for (std::string field; rest >> field;) fields.push_back(field);
  return fields;
}

double ProcessStartTime() {
  const std::vector<std::string> fields = StatFields();
  std::ifstream in("/proc/stat");
  double boot = 0;
  for (std::string key; in >> key;) {
    if (key == "btime") {
      in >> boot;
      break;
    }
  }
  if (fields.size() < 20 || boot == 0) {
    return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
  }
  return boot + std::stod(fields[19]) / ClockTicks();  // starttime, field 22: ticks after boot
}

}  // namespace

std::string ProcessMetrics(double start_time_seconds) {
  const double page = static_cast<double>(sysconf(_SC_PAGESIZE));
  double virtual_pages = 0, resident_pages = 0;
  std::ifstream("/proc/self/statm") >> virtual_pages >> resident_pages;
  int fds = 0;
  if (DIR* dir = opendir("/proc/self/fd")) {
    while (const dirent* e = readdir(dir)) {
      if (e->d_name[0] != '.') ++fds;
    }
    closedir(dir);
    --fds;  // the one opendir holds
  }
  rlimit files{};
  getrlimit(RLIMIT_NOFILE, &files);
  int threads = 0;
  std::ifstream status("/proc/self/status");
  for (std::string line; std::getline(status, line);) {
    if (line.rfind("Threads:", 0) == 0) threads = std::atoi(line.c_str() + 8);
  }
  const std::vector<std::string> stat = StatFields();
  // utime and stime, fields 14 and 15
  const double cpu = stat.size() > 12 ? (std::stod(stat[11]) + std::stod(stat[12])) / ClockTicks() : 0.0;
  return fmt::format(
      "# HELP process_resident_memory_bytes Resident memory size in bytes.\n"
      "# TYPE process_resident_memory_bytes gauge\nprocess_resident_memory_bytes {}\n"
      "# HELP process_virtual_memory_bytes Virtual memory size in bytes.\n"
      "# TYPE process_virtual_memory_bytes gauge\nprocess_virtual_memory_bytes {}\n"
      "# HELP process_open_fds Number of open file descriptors.\n"
      "# TYPE process_open_fds gauge\nprocess_open_fds {}\n"
      "# HELP process_max_fds Maximum number of open file descriptors.\n"
      "# TYPE process_max_fds gauge\nprocess_max_fds {}\n"
      "# HELP process_threads Number of OS threads in the process.\n"
      "# TYPE process_threads gauge\nprocess_threads {}\n"
      "# HELP process_cpu_seconds_total Total user and system CPU time spent in seconds.\n"
      "# TYPE process_cpu_seconds_total counter\nprocess_cpu_seconds_total {}\n"
      "# HELP process_start_time_seconds Start time of the process since unix epoch in seconds.\n"
      "# TYPE process_start_time_seconds gauge\nprocess_start_time_seconds {:.2f}\n",
      resident_pages * page, virtual_pages * page, fds, static_cast<double>(files.rlim_cur), threads, cpu,
      start_time_seconds);
}

Metrics::Metrics() : start_time_seconds_(ProcessStartTime()) {}

void Metrics::CountRequest(const std::string& method, const std::string& code, MetricsClock::time_point started) {
  const double seconds = std::chrono::duration<double>(MetricsClock::now() - started).count();
  std::lock_guard lock(mutex_);
  ++requests_[{method, code}];
  auto& histogram = handling_seconds_[method];
  if (!histogram) histogram = std::make_unique<Histogram>(kCallBuckets);
  histogram->Observe(seconds);
}

void Metrics::CountFrame(double solve_seconds, int newton_iterations, bool converged) {
  frames_.fetch_add(1, std::memory_order_relaxed);
  if (!converged) unconverged_frames_.fetch_add(1, std::memory_order_relaxed);
  newton_iterations_.fetch_add(static_cast<std::uint64_t>(newton_iterations), std::memory_order_relaxed);
  solve_seconds_.Observe(solve_seconds);
}

void Metrics::CountColliders(size_t converted) { colliders_.fetch_add(converted, std::memory_order_relaxed); }

void Metrics::HoldSolvers(int solvers, std::int64_t bytes) {
  solvers_.fetch_add(solvers, std::memory_order_relaxed);
  solver_bytes_.fetch_add(bytes, std::memory_order_relaxed);
}

std::string Metrics::Render(const std::function<std::string()>& extra) const {
  std::string out = fmt::format(
      "# HELP springblend_build_info The running springblend version.\n# TYPE springblend_build_info gauge\n"
      "springblend_build_info{{version=\"{}\"}} 1\n",
      SPRINGBLEND_VERSION);
  {
    std::lock_guard lock(mutex_);
    out += "# HELP springblend_requests_total gRPC calls by method and status code (as grpc_server_handled_total).\n"
           "# TYPE springblend_requests_total counter\n";
    for (const auto& [key, count] : requests_) {
      out += fmt::format("springblend_requests_total{{method=\"{}\",code=\"{}\"}} {}\n", key.first, key.second, count);
    }
    out += "# HELP grpc_server_handled_total Total number of RPCs completed on the server, regardless of success or "
           "failure.\n# TYPE grpc_server_handled_total counter\n";
    for (const auto& [key, count] : requests_) {
      out += fmt::format("grpc_server_handled_total{{{},grpc_code=\"{}\"}} {}\n", MethodLabels(key.first), key.second,
                         count);
    }
    out += "# HELP grpc_server_handling_seconds Time from a call's arrival to its status (uploads: with their "
           "build; Solve: the whole stream), by method.\n# TYPE grpc_server_handling_seconds histogram\n";
    for (const auto& [method, histogram] : handling_seconds_) {
      out += histogram->RenderSeries("grpc_server_handling_seconds", MethodLabels(method));
    }
  }
  out += fmt::format(
      "# HELP springblend_frames_solved_total Frames solved.\n# TYPE springblend_frames_solved_total counter\n"
      "springblend_frames_solved_total {}\n"
      "# HELP springblend_frames_unconverged_total Frames that ended without converging.\n"
      "# TYPE springblend_frames_unconverged_total counter\nspringblend_frames_unconverged_total {}\n"
      "# HELP springblend_newton_iterations_total Newton iterations over all frames.\n"
      "# TYPE springblend_newton_iterations_total counter\nspringblend_newton_iterations_total {}\n"
      "# HELP springblend_colliders_converted_total Colliders converted for Solve requests and Interactive sessions.\n"
      "# TYPE springblend_colliders_converted_total counter\nspringblend_colliders_converted_total {}\n"
      "# HELP springblend_solvers Solvers held by open Solve streams and Interactive sessions.\n"
      "# TYPE springblend_solvers gauge\nspringblend_solvers {}\n"
      "# HELP springblend_solver_memory_bytes Memory counted for those solvers (part of the request memory).\n"
      "# TYPE springblend_solver_memory_bytes gauge\nspringblend_solver_memory_bytes {}\n"
      "# HELP springblend_solve_streams Open Solve streams.\n"
      "# TYPE springblend_solve_streams gauge\nspringblend_solve_streams {}\n"
      "# HELP springblend_interactive_sessions Open Interactive sessions.\n"
      "# TYPE springblend_interactive_sessions gauge\nspringblend_interactive_sessions {}\n"
      "# HELP springblend_upload_routing_mismatches_total Uploads whose x-springblend-character header was not the "
      "id the server gave the character (a balancer may have built it on another replica than its solves').\n"
      "# TYPE springblend_upload_routing_mismatches_total counter\nspringblend_upload_routing_mismatches_total {}\n",
      frames_.load(), unconverged_frames_.load(), newton_iterations_.load(), colliders_.load(), solvers_.load(),
      solver_bytes_.load(), solve_streams.load(), interactive_sessions.load(), upload_routing_mismatches.load());
  out += solve_seconds_.Render("springblend_solve_seconds", "Time to solve one frame.");
  out += build_seconds_.Render("springblend_build_seconds",
                               "Time to build a rig (an upload's, as each upload that waited for it saw it).");
  out += queue_wait_seconds_.Render("springblend_queue_wait_seconds",
                                    "Time a solve job waited in the solve pool's queue before a worker took it.");
  out += ProcessMetrics(start_time_seconds_);
  if (extra) out += extra();
  return out;
}

MetricsEndpoint::MetricsEndpoint(const std::string& listen, std::function<std::string()> render)
    : render_(std::move(render)) {
  const auto colon = listen.rfind(':');
  sockaddr_in address{};
  address.sin_family = AF_INET;
  if (colon == std::string::npos || inet_pton(AF_INET, listen.substr(0, colon).c_str(), &address.sin_addr) != 1) {
    throw Error(ErrorCode::kInvalidInput, "--metrics " + listen + ": expected IPV4_ADDRESS:PORT");
  }
  const std::string port = listen.substr(colon + 1);
  unsigned number = 0;
  const auto [end, failure] = std::from_chars(port.data(), port.data() + port.size(), number);
  if (port.empty() || failure != std::errc() || end != port.data() + port.size() || number > 65535) {
    throw Error(ErrorCode::kInvalidInput, "--metrics " + listen + ": expected IPV4_ADDRESS:PORT (port 0 to 65535)");
  }
  address.sin_port = htons(static_cast<std::uint16_t>(number));
  socket_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  const int one = 1;
  setsockopt(socket_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
  if (socket_ < 0 || ::bind(socket_, reinterpret_cast<sockaddr*>(&address), sizeof(address)) != 0 ||
      ::listen(socket_, 16) != 0) {
    if (socket_ >= 0) ::close(socket_);
    throw Error(ErrorCode::kInvalidInput, "cannot serve metrics on " + listen + ": " + std::strerror(errno));
  }
  socklen_t length = sizeof(address);
  getsockname(socket_, reinterpret_cast<sockaddr*>(&address), &length);
  port_ = ntohs(address.sin_port);
  thread_ = std::thread([this] { Serve(); });
}

MetricsEndpoint::~MetricsEndpoint() {
  stopping_ = true;
  ::shutdown(socket_, SHUT_RDWR);  // wakes accept()
  ::close(socket_);
  if (thread_.joinable()) thread_.join();
}

// One thread serves every connection with poll(): a connection that sends nothing (or only part of a request)
// waits in the poll set, never in front of a scraper; it is dropped after 2 s, and the oldest is dropped when
// kMaxConnections are open. Answers are small (a few KiB) and sent with a 1 s send timeout.
void MetricsEndpoint::Serve() {
  constexpr size_t kMaxConnections = 64;
  constexpr auto kRequestTimeout = std::chrono::seconds(2);
  struct Connection {
    int fd;
    std::chrono::steady_clock::time_point deadline;
    std::string request;
  };
  std::vector<Connection> connections;
  const auto respond = [&](Connection& c) {
    std::string response;
    if (c.request.rfind("GET / ", 0) == 0) {
      const std::string body = "<a href=\"/metrics\">springblend-server metrics at /metrics</a>\n";
      response = fmt::format("HTTP/1.0 200 OK\r\nContent-Type: text/html; charset=utf-8\r\n"
                             "Content-Length: {}\r\nConnection: close\r\n\r\n{}",
                             body.size(), body);
    } else if (c.request.rfind("GET /metrics", 0) == 0) {
      const std::string body = render_();
      response = fmt::format("HTTP/1.0 200 OK\r\nContent-Type: text/plain; version=0.0.4; charset=utf-8\r\n"
                             "Content-Length: {}\r\nConnection: close\r\n\r\n{}",
                             body.size(), body);
    } else {
      response = "HTTP/1.0 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n";
    }
    ::fcntl(c.fd, F_SETFL, ::fcntl(c.fd, F_GETFL) & ~O_NONBLOCK);
    timeval timeout{1, 0};
    setsockopt(c.fd, SOL_SOCKET, SO_SNDTIMEO, &timeout, sizeof(timeout));
    size_t sent = 0;
    while (sent < response.size()) {
      const ssize_t m = ::send(c.fd, response.data() + sent, response.size() - sent, MSG_NOSIGNAL);
      if (m <= 0) break;
      sent += static_cast<size_t>(m);
    }
  };
  while (!stopping_) {
    std::vector<pollfd> polled{{socket_, POLLIN, 0}};
    for (const auto& c : connections) polled.push_back({c.fd, POLLIN, 0});
    ::poll(polled.data(), polled.size(), 200);
    if (stopping_) break;
    const auto now = std::chrono::steady_clock::now();
    std::vector<Connection> open;
    for (size_t i = 0; i < connections.size(); ++i) {
      Connection& c = connections[i];
      bool keep = now < c.deadline;
      if (keep && (polled[i + 1].revents & (POLLIN | POLLHUP | POLLERR)) != 0) {
        char buffer[1024];
        const ssize_t n = ::recv(c.fd, buffer, sizeof(buffer), MSG_DONTWAIT);
        if (n <= 0) {
          keep = false;
        } else {
          c.request.append(buffer, static_cast<size_t>(n));
          // The request line is all we look at; answer once it is complete (or the request is oversized).
          if (c.request.find('\n') != std::string::npos || c.request.size() >= 4096) {
            respond(c);
            keep = false;
          }
        }
      }
      if (keep) {
        open.push_back(std::move(c));
      } else {
        ::close(c.fd);
      }
    }
    connections = std::move(open);
    if ((polled[0].revents & POLLIN) != 0) {
      const int client = ::accept4(socket_, nullptr, nullptr, SOCK_CLOEXEC | SOCK_NONBLOCK);
      if (client >= 0) {
        if (connections.size() >= kMaxConnections) {
          ::close(connections.front().fd);
          connections.erase(connections.begin());
        }
        connections.push_back({client, now + kRequestTimeout, {}});
      }
    }
  }
  for (const auto& c : connections) ::close(c.fd);
}

}  // namespace springblend::server
