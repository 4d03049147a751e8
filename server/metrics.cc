#include "metrics.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <fcntl.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <charconv>
#include <chrono>
#include <vector>
#include <cstring>
#include <fmt/format.h>

#include "springblend/error.h"
#include "springblend/version.h"

namespace springblend::server {

void Histogram::Observe(double value) {
  size_t bucket = 0;
  while (bucket < kBounds.size() && value > kBounds[bucket]) ++bucket;
  buckets_[bucket].fetch_add(1, std::memory_order_relaxed);
  count_.fetch_add(1, std::memory_order_relaxed);
  double sum = sum_.load(std::memory_order_relaxed);
  while (!sum_.compare_exchange_weak(sum, sum + value, std::memory_order_relaxed)) {
  }
}

std::string Histogram::Render(const std::string& name, const std::string& help, double scale) const {
  std::string out = fmt::format("# HELP {} {}\n# TYPE {} histogram\n", name, help, name);
  std::uint64_t cumulative = 0;
  for (size_t b = 0; b < kBounds.size(); ++b) {
    cumulative += buckets_[b].load(std::memory_order_relaxed);
    out += fmt::format("{}_bucket{{le=\"{}\"}} {}\n", name, kBounds[b] * scale, cumulative);
  }
  cumulative += buckets_[kBounds.size()].load(std::memory_order_relaxed);
  out += fmt::format("{}_bucket{{le=\"+Inf\"}} {}\n{}_sum {}\n{}_count {}\n", name, cumulative, name,
                     sum_.load(std::memory_order_relaxed), name, count_.load(std::memory_order_relaxed));
  return out;
}

void Metrics::CountRequest(const std::string& method, const std::string& code) {
  std::lock_guard lock(mutex_);
  ++requests_[{method, code}];
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
  out += "# HELP springblend_requests_total gRPC calls by method and status code.\n"
                    "# TYPE springblend_requests_total counter\n";
  {
    std::lock_guard lock(mutex_);
    for (const auto& [key, count] : requests_) {
      out += fmt::format("springblend_requests_total{{method=\"{}\",code=\"{}\"}} {}\n", key.first, key.second, count);
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
      "# TYPE springblend_solver_memory_bytes gauge\nspringblend_solver_memory_bytes {}\n",
      frames_.load(), unconverged_frames_.load(), newton_iterations_.load(), colliders_.load(), solvers_.load(),
      solver_bytes_.load());
  out += solve_seconds_.Render("springblend_solve_seconds", "Time to solve one frame.");
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
    if (c.request.rfind("GET /metrics", 0) == 0) {
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
