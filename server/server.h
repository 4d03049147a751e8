// The farm server composed from its options: the character store over the cache directory, the solver and
// metadata pools, limits, memory budget, watchdog, tokens and TLS, the gRPC services (with standard health
// and reflection), and optionally the Prometheus endpoint and the plaintext health-only port. main() only turns
// flags into ServerOptions; tests and embedders create a Server directly and may talk to it in-process.
//
//   ServerOptions options;
//   options.listen = {};                        // no network port: in-process only
//   options.cache_dir = dir;
//   auto server = Server::Create(options);
//   springblend::Client client(server->InProcessChannel());
//   ...
//   server->Shutdown();                          // drains in-flight calls, then stops
#pragma once

#include <grpcpp/channel.h>
#include <grpcpp/support/channel_arguments.h>

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "character_store.h"
#include "convert.h"
#include "security.h"
#include "watchdog.h"

namespace springblend::server {

struct ServerOptions {
  // HOST:PORT addresses to serve on (port 0 picks a free one; addresses() tells which). Empty: no network
  // port at all, only InProcessChannel.
  std::vector<std::string> listen = {"127.0.0.1:50051"};
  TlsOptions tls;  // on every listen address; plaintext without a certificate

  // Bearer tokens: each of `tokens` has the full role; `tokens_file` holds "ROLE TOKEN" lines. With none,
  // every call is allowed.
  std::vector<std::string> tokens;
  std::string tokens_file;

  std::string cache_dir;                         // uploads, shared by replicas; empty: memory only
  std::int64_t memory_budget_bytes = 4LL << 30;  // built characters in memory (least recently used out first)
  int workers = 0;                               // solver threads (solves and sessions); 0: the core count
  int queue = 64;                                // jobs waiting for a worker before RESOURCE_EXHAUSTED
  // Rig builds (uploads, rebuilds from the cache directory) run on threads of their own, never on the solver
  // threads: this many at once, and this many more queued before RESOURCE_EXHAUSTED.
  int build_workers = 1;
  int build_queue = 16;
  int metadata_workers = 2;                      // threads for Get/List/Delete, never behind a solve
  Limits limits;                                 // sizes and counts of requests (over: RESOURCE_EXHAUSTED)
  std::int64_t request_memory_bytes = 2LL << 30;  // uploads in progress and open streams together
  StreamTimeouts timeouts;                       // stalled streams, idle Interactive sessions
  std::string replica_name;                      // every frame's served_by; empty: the host name
  int max_receive_message_bytes = 64 << 20;
  // Cache files kept open for the characters in memory to read their target paths from; past it the least
  // recently read are closed and opened again when read (springblend/open_files.h). 0: half the process's
  // RLIMIT_NOFILE soft limit (at least 16), leaving the rest for connections and files being written.
  int max_open_cache_files = 0;

  std::string metrics_listen;  // HOST:PORT of the Prometheus endpoint (GET /metrics); empty: off
  std::string health_listen;   // HOST:PORT of a plaintext port serving only grpc.health.v1; empty: off
  // How long Shutdown lets in-flight calls finish before cancelling them.
  std::chrono::milliseconds drain{std::chrono::seconds(30)};

  // Throws Error(kInvalidInput) naming the field when a value is out of range.
  void Validate() const;
  // max_open_cache_files, or its default when 0.
  int OpenCacheFileLimit() const;
};

// What the server holds and does right now, for tests and the metrics endpoint.
struct ServerStats {
  StoreStats store;
  CharacterStore::Cleanup cleanup;  // what start-up removed from the cache directory
  int workers = 0, workers_busy = 0, queue_depth = 0;
  std::int64_t request_memory_bytes = 0;  // of ServerOptions::request_memory_bytes in use
};

class Server {
 public:
  // Validates the options, opens the cache directory (removing what writers killed mid-write left), starts
  // the pools and serves. Throws Error(kInvalidInput) naming the option at fault (a bad address, a port that
  // is taken, an unreadable TLS or tokens file).
  static std::unique_ptr<Server> Create(ServerOptions options);
  ~Server();  // Shutdown with no drain unless already shut down, then waits
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  // The bound HOST:PORT of each listen address, in order.
  const std::vector<std::string>& addresses() const;
  int metrics_port() const;  // 0 when off
  int health_port() const;   // 0 when off
  // A channel straight into this server, without a socket (no TLS; tokens still apply). gRPC's in-process
  // transport ends its calls when the server shuts down: they are cancelled by Shutdown, not drained.
  std::shared_ptr<grpc::Channel> InProcessChannel(const grpc::ChannelArguments& arguments = {});

  // Drains: health says NOT_SERVING at once (on both ports), new calls are refused, in-flight calls get
  // ServerOptions::drain to finish and are cancelled after. Returns when every call has ended. Idempotent; may
  // be called from any thread (a signal thread) while another is in Wait.
  void Shutdown();
  // Blocks until Shutdown has finished.
  void Wait();

  ServerStats stats() const;
  // Everything the metrics endpoint serves, in Prometheus' text format.
  std::string MetricsText() const;

 private:
  struct State;
  explicit Server(std::unique_ptr<State> state);
  std::unique_ptr<State> state_;
};

// $XDG_CACHE_HOME/springblend, else ~/.cache/springblend, else ./springblend-cache.
std::string DefaultCacheDirectory();
// Throws Error(kInvalidInput) naming `flag` unless `address` is HOST:PORT with a port from 0 to 65535 (gRPC
// takes larger ports without complaint).
void CheckListenAddress(const std::string& address, const std::string& flag);
// The valid ranges of --max-upload-bytes, --max-vertices and --max-frames (Limits).
inline constexpr std::int64_t kMinUploadBytes = 1 << 10, kMaxUploadBytes = std::int64_t{1} << 40;
inline constexpr int kMinVertices = 3, kMaxVertices = 100'000'000, kMaxFrames = 10'000'000;

}  // namespace springblend::server
