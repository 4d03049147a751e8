// springblend-server: the farm server. main only turns flags into ServerOptions, creates the Server (server.h)
// and runs it until SIGTERM or SIGINT, then drains in-flight calls.
#include <signal.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <chrono>
#include <iostream>
#include <thread>

#include "access_log.h"
#include "server.h"
#include "springblend/runtime.h"
#include "springblend/version.h"

int main(int argc, char** argv) {
  springblend::ConfigureNumericalThreads(argv);
  using namespace springblend::server;

  CLI::App app{"springblend-server: caches characters' spring structures and streams solved blendshapes"};
  app.set_version_flag("--version", std::string("springblend-server ") + SPRINGBLEND_VERSION);
  ServerOptions o;
  o.workers = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  std::int64_t memory_mb = 4096, request_memory_mb = 2048;
  int max_collider_faces = o.limits.collider.max_faces;
  double stall_seconds = 60, idle_seconds = 600;
  int drain_seconds = 30;
  app.add_option("--listen", o.listen, "address:port to serve on (port 0 picks a free one); repeatable");
  app.add_option("--cache-dir", o.cache_dir, "directory of uploaded characters, shared by replicas (default: "
                                             "$XDG_CACHE_HOME/springblend or ~/.cache/springblend)");
  app.add_option("--workers", o.workers, "solver threads")->check(CLI::Range(1, 1024));
  app.add_option("--queue", o.queue, "jobs waiting for a solver thread before RESOURCE_EXHAUSTED")->check(CLI::Range(1, 100000));
  app.add_option("--memory-budget-mb", memory_mb, "memory for built characters; least recently used go first")->check(CLI::Range(1, 1 << 20));
  app.add_option("--max-open-cache-files", o.max_open_cache_files,
                 "cache files kept open for the characters in memory to read their paths from; past it the least "
                 "recently read are closed and reopened when read (default: half the open-file limit, at least 16)")
      ->check(CLI::Range(1, 1'000'000));
  app.add_option("--max-upload-bytes", o.limits.max_upload_bytes, "largest upload")
      ->check(CLI::Range(kMinUploadBytes, kMaxUploadBytes));
  app.add_option("--max-vertices", o.limits.max_vertices, "most vertices in a character")
      ->check(CLI::Range(kMinVertices, kMaxVertices));
  app.add_option("--max-frames", o.limits.max_frames, "most frames in one solve request (more: RESOURCE_EXHAUSTED)")
      ->check(CLI::Range(1, kMaxFrames));
  app.add_option("--max-collider-faces", max_collider_faces,
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
  app.add_option("--build-workers", o.build_workers,
                 "threads for rig builds (uploads, rebuilds from --cache-dir), apart from the solver threads")
      ->check(CLI::Range(1, 64));
  app.add_option("--build-queue", o.build_queue, "builds waiting for a build thread before RESOURCE_EXHAUSTED")
      ->check(CLI::Range(0, 100000));
  app.add_option("--metadata-workers", o.metadata_workers,
                 "threads for GetCharacter, ListCharacters and DeleteCharacter, apart from the solver threads")
      ->check(CLI::Range(1, 64));
  app.add_option("--replica-name", o.replica_name, "name reported in each frame's served_by (default: host name)");
  app.add_option("--drain-seconds", drain_seconds, "on SIGTERM, how long in-flight streams may finish")
      ->check(CLI::Range(0, 86400));
  app.add_option("--metrics", o.metrics_listen, "serve Prometheus metrics at http://ADDRESS:PORT/metrics (off when empty)");
  app.add_option("--health-address", o.health_listen,
                 "also serve only the standard health service, over plaintext, at HOST:PORT: for probes that "
                 "cannot speak TLS (off when empty)");
  app.add_option("--tls-cert", o.tls.cert_file, "PEM certificate chain: serve TLS instead of plaintext");
  app.add_option("--tls-key", o.tls.key_file, "PEM private key of --tls-cert");
  app.add_option("--tls-client-ca", o.tls.client_ca_file,
                 "PEM CA bundle: require every client to present a certificate it signed (mutual TLS)");
  app.add_option("--token", o.tokens, "a token with the full role (upload, delete, solve); repeatable. "
                                      "Prefer --tokens-file: flags show in ps");
  app.add_option("--tokens-file", o.tokens_file, "file of 'ROLE TOKEN' lines (ROLE: full or solve); with any "
                                                 "token, calls without an accepted one are refused");
  std::string log_format = "text";
  app.add_option("--log-format", log_format,
                 "text (spdlog's lines) or json (one object per line: time, level, message; a call's access line "
                 "carries method, character, frames, status, ms, peer and request_id as members)")
      ->check(CLI::IsMember({"text", "json"}));
  CLI11_PARSE(app, argc, argv);
  if (o.cache_dir.empty()) o.cache_dir = DefaultCacheDirectory();
  o.memory_budget_bytes = memory_mb << 20;
  o.request_memory_bytes = request_memory_mb << 20;
  o.limits.SetMaxColliderFaces(max_collider_faces);
  o.timeouts.stall = std::chrono::milliseconds(static_cast<std::int64_t>(stall_seconds * 1000));
  o.timeouts.idle = std::chrono::milliseconds(static_cast<std::int64_t>(idle_seconds * 1000));
  o.drain = std::chrono::seconds(drain_seconds);

  // Logs go to stderr; stdout carries only the "listening on" lines, for scripts and tests to read.
  spdlog::set_default_logger(log_format == "json" ? spdlog::stderr_logger_mt("springblend")
                                                  : spdlog::stderr_color_mt("springblend"));
  springblend::server::SetJsonLogs(log_format == "json");
  // A closed stdout or a vanished peer must not kill a shared server.
  signal(SIGPIPE, SIG_IGN);
  // Signals go to a dedicated thread (blocked everywhere else, so set before any thread starts).
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  try {
    const std::unique_ptr<Server> server = Server::Create(o);
    if (server->metrics_port() != 0) {
      std::cout << "springblend-server metrics on http://" << o.metrics_listen.substr(0, o.metrics_listen.rfind(':'))
                << ":" << server->metrics_port() << "/metrics" << std::endl;
    }
    if (server->health_port() != 0) {
      std::cout << "springblend-server health on " << o.health_listen.substr(0, o.health_listen.rfind(':')) << ":"
                << server->health_port() << std::endl;
    }
    for (const auto& address : server->addresses()) {
      std::cout << "springblend-server listening on " << address << std::endl;
    }
    std::thread stopper([&] {
      int signal_number = 0;
      sigwait(&signals, &signal_number);
      spdlog::info("signal {}: draining in-flight calls for up to {} s", signal_number, drain_seconds);
      server->Shutdown();
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
