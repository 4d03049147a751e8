// springblend-server: the farm server. main only reads flags, builds the services and runs them until
// SIGTERM or SIGINT, then drains in-flight streams.
#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/grpcpp.h>
#include <signal.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>
#include <unistd.h>
#include <fmt/format.h>

#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <thread>

#include "character_store.h"
#include "health.h"
#include "metrics.h"
#include "security.h"
#include "service.h"
#include "solver_pool.h"
#include "springblend/error.h"
#include "springblend/runtime.h"
#include "springblend/version.h"

int main(int argc, char** argv) {
  springblend::ConfigureNumericalThreads(argv);
  using namespace springblend::server;

  CLI::App app{"springblend-server: caches characters' spring structures and streams solved blendshapes"};
  app.set_version_flag("--version", std::string("springblend-server ") + SPRINGBLEND_VERSION);
  std::string listen = "127.0.0.1:50051";
  std::string cache_dir;
  int workers = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  int queue = 64;
  std::int64_t memory_mb = 4096;
  Limits limits;
  std::int64_t request_memory_mb = 2048;
  double stall_seconds = 60, idle_seconds = 600;
  int metadata_workers = 2;
  std::string replica;
  int drain_seconds = 30;
  std::string metrics_listen;
  std::string health_listen;
  TlsOptions tls;
  std::vector<std::string> tokens;
  std::string tokens_file;
  app.add_option("--listen", listen, "address:port to serve on (port 0 picks a free one)");
  app.add_option("--cache-dir", cache_dir, "directory of uploaded characters, shared by replicas (default: "
                                           "$XDG_CACHE_HOME/springblend or ~/.cache/springblend)");
  app.add_option("--workers", workers, "solver threads")->check(CLI::Range(1, 1024));
  app.add_option("--queue", queue, "jobs waiting for a solver thread before RESOURCE_EXHAUSTED")->check(CLI::Range(1, 100000));
  app.add_option("--memory-budget-mb", memory_mb, "memory for built characters; least recently used go first")->check(CLI::Range(1, 1 << 20));
  app.add_option("--max-upload-bytes", limits.max_upload_bytes, "largest upload");
  app.add_option("--max-vertices", limits.max_vertices, "most vertices in a character");
  app.add_option("--max-frames", limits.max_frames, "most frames in one solve request (more: RESOURCE_EXHAUSTED)");
  app.add_option("--max-collider-faces", limits.collider.max_faces,
                 "most triangles (and vertices) in one mesh collider; checked before the mesh is built")
      ->check(CLI::Range(4, 10'000'000));
  app.add_option("--request-memory-mb", request_memory_mb,
                 "memory for uploads in progress and open Solve/Interactive streams together; over it a new one "
                 "gets RESOURCE_EXHAUSTED")
      ->check(CLI::Range(1, 1 << 20));
  app.add_option("--stall-seconds", stall_seconds,
                 "cancel a stream whose client has not read a sent frame (or sent its next upload piece) for this long")
      ->check(CLI::Range(0.05, 1e6));
  app.add_option("--idle-seconds", idle_seconds, "cancel an Interactive session with no message for this long")
      ->check(CLI::Range(0.05, 1e7));
  app.add_option("--metadata-workers", metadata_workers,
                 "threads for GetCharacter, ListCharacters and DeleteCharacter, apart from the solver threads")
      ->check(CLI::Range(1, 64));
  app.add_option("--replica-name", replica, "name reported in each frame's served_by (default: host name)");
  app.add_option("--drain-seconds", drain_seconds, "on SIGTERM, how long in-flight streams may finish");
  app.add_option("--metrics", metrics_listen, "serve Prometheus metrics at http://ADDRESS:PORT/metrics (off when empty)");
  app.add_option("--health-address", health_listen,
                 "also serve only the standard health service, over plaintext, at HOST:PORT: for probes that "
                 "cannot speak TLS (off when empty)");
  app.add_option("--tls-cert", tls.cert_file, "PEM certificate chain: serve TLS instead of plaintext");
  app.add_option("--tls-key", tls.key_file, "PEM private key of --tls-cert");
  app.add_option("--tls-client-ca", tls.client_ca_file,
                 "PEM CA bundle: require every client to present a certificate it signed (mutual TLS)");
  app.add_option("--token", tokens, "a token with the full role (upload, delete, solve); repeatable. "
                                    "Prefer --tokens-file: flags show in ps");
  app.add_option("--tokens-file", tokens_file, "file of 'ROLE TOKEN' lines (ROLE: full or solve); with any "
                                               "token, calls without an accepted one are refused");
  CLI11_PARSE(app, argc, argv);

  // Logs go to stderr; stdout carries only the "listening on" line, for scripts and tests to read.
  spdlog::set_default_logger(spdlog::stderr_color_mt("springblend"));
  // A closed stdout or a vanished peer must not kill a shared server.
  signal(SIGPIPE, SIG_IGN);
  if (cache_dir.empty()) {
    const char* xdg = std::getenv("XDG_CACHE_HOME");
    const char* home = std::getenv("HOME");
    cache_dir = xdg ? std::string(xdg) + "/springblend" : home ? std::string(home) + "/.cache/springblend" : "springblend-cache";
  }
  if (replica.empty()) {
    char host[256] = {0};
    gethostname(host, sizeof(host) - 1);
    replica = host;
  }

  // Signals go to a dedicated thread (blocked everywhere else, so set before any thread starts).
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  try {
    TokenAuthenticator auth;
    for (const auto& t : tokens) auth.Add(t, Role::kFull);
    if (!tokens_file.empty()) auth.AddFile(tokens_file);
    const std::shared_ptr<grpc::ServerCredentials> credentials = MakeServerCredentials(tls);
    CharacterStore store({cache_dir, memory_mb << 20});
    // Before serving: what writers killed mid-write (kill -9, OOM) left behind. Live writers' files are kept.
    const CharacterStore::Cleanup cleanup = store.RemoveStaleTemporaries();
    spdlog::info("cache {}: removed {} stale temporary files{}", cache_dir, cleanup.removed,
                 cleanup.in_use ? fmt::format(" ({} in use by another writer, kept)", cleanup.in_use) : "");
    limits.collider.max_vertices = limits.collider.max_faces;
    limits.collider_text.max_faces = limits.collider.max_faces;
    limits.collider_text.max_vertices = limits.collider.max_faces;
    SolverPool pool(workers, queue);
    SolverPool metadata_pool(metadata_workers, queue);
    Metrics metrics;
    MemoryBudget memory(request_memory_mb << 20);
    Watchdog watchdog({std::chrono::milliseconds(static_cast<std::int64_t>(stall_seconds * 1000)),
                       std::chrono::milliseconds(static_cast<std::int64_t>(idle_seconds * 1000))});
    ServiceContext context{store, pool, metadata_pool, limits, replica, metrics, auth, memory, watchdog};
    std::unique_ptr<MetricsEndpoint> metrics_endpoint;
    if (!metrics_listen.empty()) {
      metrics_endpoint = std::make_unique<MetricsEndpoint>(metrics_listen, [&] {
        return metrics.Render([&] {
          const StoreStats s = store.stats();
          return fmt::format(
              "# TYPE springblend_cache_hits_total counter\nspringblend_cache_hits_total {}\n"
              "# TYPE springblend_cache_misses_total counter\nspringblend_cache_misses_total {}\n"
              "# TYPE springblend_cache_evictions_total counter\nspringblend_cache_evictions_total {}\n"
              "# TYPE springblend_cache_rebuilds_from_disk_total counter\nspringblend_cache_rebuilds_from_disk_total {}\n"
              "# TYPE springblend_cache_corrupt_files_total counter\nspringblend_cache_corrupt_files_total {}\n"
              "# TYPE springblend_cache_bytes gauge\nspringblend_cache_bytes {}\n"
              "# TYPE springblend_cache_characters gauge\nspringblend_cache_characters {}\n"
              "# TYPE springblend_queue_depth gauge\nspringblend_queue_depth {}\n"
              "# TYPE springblend_workers_busy gauge\nspringblend_workers_busy {}\n"
              "# TYPE springblend_workers gauge\nspringblend_workers {}\n"
              "# TYPE springblend_request_memory_bytes gauge\nspringblend_request_memory_bytes {}\n",
              s.hits, s.misses, s.evictions, s.rebuilds_from_disk, s.corrupt_files, s.bytes, s.characters,
              pool.queue_depth(), pool.busy(), pool.threads(), memory.used());
        });
      });
      std::cout << "springblend-server metrics on http://" << metrics_listen.substr(0, metrics_listen.rfind(':'))
                << ":" << metrics_endpoint->port() << "/metrics" << std::endl;
    }
    CharacterServiceImpl characters(context);
    SolveServiceImpl solves(context);

    grpc::EnableDefaultHealthCheckService(true);
    grpc::reflection::InitProtoReflectionServerBuilderPlugin();
    grpc::ServerBuilder builder;
    int port = 0;
    builder.AddListeningPort(listen, credentials, &port);
    builder.RegisterService(&characters);
    builder.RegisterService(&solves);
    builder.SetMaxReceiveMessageSize(64 << 20);
    std::vector<std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface>> interceptors;
    interceptors.push_back(MakeReflectionGuard(auth));
    builder.experimental().SetInterceptorCreators(std::move(interceptors));
    std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
    if (!server || port == 0) {
      std::cerr << "springblend-server: cannot listen on " << listen << "\n";
      return 2;
    }
    const std::string host = listen.substr(0, listen.rfind(':'));
    // Started once the main server is up, so it says SERVING only when the main port does.
    std::unique_ptr<HealthEndpoint> health;
    if (!health_listen.empty()) {
      health = std::make_unique<HealthEndpoint>(health_listen);
      const std::string health_host = health_listen.substr(0, health_listen.rfind(':'));
      std::cout << "springblend-server health on " << health_host << ":" << health->port() << std::endl;
      spdlog::info("springblend-server {}: health (grpc.health.v1.Health only, plaintext) on {}:{}",
                   SPRINGBLEND_VERSION, health_host, health->port());
    }
    std::cout << "springblend-server listening on " << host << ":" << port << std::endl;
    spdlog::info("springblend-server {} listening on {}:{} with {} solver threads, cache {}", SPRINGBLEND_VERSION, host,
                 port, workers, cache_dir);
    spdlog::info("transport: {}; {}", tls.cert_file.empty()         ? "plaintext"
                                      : tls.client_ca_file.empty() ? "TLS"
                                                                   : "mutual TLS",
                 auth.enabled() ? fmt::format("{} accepted tokens", auth.size()) : std::string("no tokens: open"));
    if (auth.enabled() && tls.cert_file.empty() && host != "127.0.0.1" && host != "localhost" && host != "[::1]") {
      spdlog::warn("tokens travel in the clear on {}: add --tls-cert and --tls-key", host);
    }

    std::thread stopper([&] {
      int signal_number = 0;
      sigwait(&signals, &signal_number);
      spdlog::info("signal {}: draining in-flight calls for up to {} s", signal_number, drain_seconds);
      // Probes see NOT_SERVING while in-flight calls drain, so balancers stop sending new ones.
      if (auto* main_health = server->GetHealthCheckService()) main_health->SetServingStatus(false);
      if (health) health->SetServing(false);
      server->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(drain_seconds));
    });
    server->Wait();
    stopper.join();
    spdlog::info("stopped");
  } catch (const std::exception& e) {
    std::cerr << "springblend-server: " << e.what() << "\n";
    return 2;
  }
  return 0;
}
