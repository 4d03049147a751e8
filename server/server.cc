#include "server.h"

#include <fmt/format.h>
#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/server.h>
#include <grpcpp/server_builder.h>
#include <spdlog/spdlog.h>
#include <sys/resource.h>
#include <unistd.h>

#include <cstdlib>
#include <mutex>
#include <thread>

#include "health.h"
#include "memory_budget.h"
#include "metrics.h"
#include "service.h"
#include "solver_pool.h"
#include "springblend/error.h"
#include "springblend/open_files.h"
#include "springblend/version.h"

namespace springblend::server {
namespace {

[[noreturn]] void Invalid(const std::string& what) { throw Error(ErrorCode::kInvalidInput, what); }

void CheckRange(const char* field, std::int64_t value, std::int64_t low, std::int64_t high) {
  if (value < low || value > high) Invalid(fmt::format("{} = {} is outside [{}, {}]", field, value, low, high));
}

std::string HostOf(const std::string& address) { return address.substr(0, address.rfind(':')); }
std::string PortOf(const std::string& address) { return address.substr(address.rfind(':') + 1); }
bool AnyHost(const std::string& host) { return host.empty() || host == "0.0.0.0" || host == "[::]" || host == "::"; }

std::string HostName() {
  char host[256] = {0};
  gethostname(host, sizeof(host) - 1);
  return host;
}

TokenAuthenticator MakeAuthenticator(const ServerOptions& options) {
  TokenAuthenticator auth;
  for (const auto& t : options.tokens) auth.Add(t, Role::kFull);
  if (!options.tokens_file.empty()) auth.AddFile(options.tokens_file);
  return auth;
}

}  // namespace

void CheckListenAddress(const std::string& address, const std::string& flag) {
  const size_t colon = address.rfind(':');
  const std::string port = colon == std::string::npos ? "" : address.substr(colon + 1);
  if (colon == 0 || port.empty() || port.size() > 5 || port.find_first_not_of("0123456789") != std::string::npos ||
      std::stoi(port) > 65535) {
    Invalid(flag + " " + address + ": expected HOST:PORT (port 0 to 65535)");
  }
}

std::string DefaultCacheDirectory() {
  if (const char* xdg = std::getenv("XDG_CACHE_HOME")) return std::string(xdg) + "/springblend";
  if (const char* home = std::getenv("HOME")) return std::string(home) + "/.cache/springblend";
  return "springblend-cache";
}

int ServerOptions::OpenCacheFileLimit() const {
  if (max_open_cache_files > 0) return max_open_cache_files;
  struct rlimit files {};
  const rlim_t soft = ::getrlimit(RLIMIT_NOFILE, &files) == 0 ? files.rlim_cur : 1024;
  return static_cast<int>(std::max<rlim_t>(16, std::min<rlim_t>(soft, 2'000'000) / 2));
}

void ServerOptions::Validate() const {
  for (const auto& address : listen) CheckListenAddress(address, "--listen");
  CheckRange("workers", workers, 0, 1024);
  CheckRange("queue", queue, 1, 100'000);
  CheckRange("metadata_workers", metadata_workers, 1, 64);
  CheckRange("build_workers", build_workers, 1, 64);
  CheckRange("build_queue", build_queue, 0, 100'000);
  CheckRange("memory_budget_bytes", memory_budget_bytes, 1, std::int64_t{1} << 50);
  CheckRange("request_memory_bytes", request_memory_bytes, 1, std::int64_t{1} << 50);
  CheckRange("max_upload_bytes (--max-upload-bytes)", limits.max_upload_bytes, kMinUploadBytes, kMaxUploadBytes);
  CheckRange("max_vertices (--max-vertices)", limits.max_vertices, kMinVertices, kMaxVertices);
  CheckRange("max_frames (--max-frames)", limits.max_frames, 1, kMaxFrames);
  CheckRange("max_receive_message_bytes", max_receive_message_bytes, 1 << 10, 1 << 30);
  CheckRange("max_open_cache_files (--max-open-cache-files)", max_open_cache_files, 0, 1'000'000);
  if (timeouts.stall.count() <= 0 || timeouts.idle.count() <= 0) Invalid("timeouts: stall and idle must be positive");
  if (drain.count() < 0) Invalid("drain must not be negative");
  if (!metrics_listen.empty()) CheckListenAddress(metrics_listen, "--metrics");
  if (!health_listen.empty()) {
    CheckListenAddress(health_listen, "--health-address");
    // Two servers on one port (gRPC would otherwise share it with SO_REUSEPORT) split the connections.
    for (const auto& address : listen) {
      const std::string host = HostOf(address), health_host = HostOf(health_listen);
      if (PortOf(address) == PortOf(health_listen) && std::stoi(PortOf(address)) != 0 &&
          (host == health_host || AnyHost(host) || AnyHost(health_host))) {
        Invalid("--health-address " + health_listen + " is the port of --listen " + address +
                ": give the health service a port of its own");
      }
    }
  }
}

// Members in the order they are built; destroyed in reverse, so the endpoints and the gRPC server go before the
// services, the services before the pools (which finish their queued jobs), the pools before what jobs use.
struct Server::State {
  explicit State(ServerOptions o)
      : options(std::move(o)),
        auth(MakeAuthenticator(options)),
        credentials(MakeServerCredentials(options.tls)),
        store(StoreOptionsOf(options, drain)),
        cleanup(store.RemoveStaleTemporaries()),
        memory(options.request_memory_bytes),
        watchdog(options.timeouts),
        pool(options.workers, options.queue, [this](double seconds) { metrics.ObserveQueueWait(seconds); }),
        metadata_pool(options.metadata_workers, options.queue),
        context{store, pool, metadata_pool, options.limits, options.replica_name, metrics, auth, memory, watchdog,
                drain},
        characters(context),
        solves(context) {}

  static StoreOptions StoreOptionsOf(const ServerOptions& o, const DrainDeadline& drain) {
    StoreOptions store;
    store.directory = o.cache_dir;
    store.memory_budget_bytes = o.memory_budget_bytes;
    store.build_threads = o.build_workers;
    store.build_queue = o.build_queue;
    store.stop = [&drain] { return drain.Passed(); };  // a build running at shutdown stops once the drain is over
    return store;
  }

  ServerOptions options;
  DrainDeadline drain;  // before the store: its builds ask it until the store's threads end
  TokenAuthenticator auth;
  std::shared_ptr<grpc::ServerCredentials> credentials;
  CharacterStore store;
  CharacterStore::Cleanup cleanup;
  Metrics metrics;
  MemoryBudget memory;
  Watchdog watchdog;
  SolverPool pool;
  SolverPool metadata_pool;
  ServiceContext context;
  CharacterServiceImpl characters;
  SolveServiceImpl solves;
  std::unique_ptr<grpc::Server> server;
  std::vector<std::string> addresses;
  std::unique_ptr<HealthEndpoint> health;
  std::unique_ptr<MetricsEndpoint> metrics_endpoint;
  std::once_flag shutdown;
};

std::unique_ptr<Server> Server::Create(ServerOptions options) {
  options.Validate();
  if (options.workers == 0) options.workers = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  if (options.replica_name.empty()) options.replica_name = HostName();
  auto state = std::make_unique<State>(std::move(options));
  const ServerOptions& o = state->options;
  if (!o.cache_dir.empty()) {
    spdlog::info("cache {}: removed {} stale temporary files{}", o.cache_dir, state->cleanup.removed,
                 state->cleanup.in_use ? fmt::format(" ({} in use by another writer, kept)", state->cleanup.in_use)
                                       : "");
  }

  // Each character in memory reads its paths from its cache file: a bounded number of those stay open.
  SetOpenPathFileLimit(o.OpenCacheFileLimit());

  grpc::EnableDefaultHealthCheckService(true);
  grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  std::vector<int> ports(o.listen.size(), 0);
  for (size_t i = 0; i < o.listen.size(); ++i) builder.AddListeningPort(o.listen[i], state->credentials, &ports[i]);
  builder.RegisterService(&state->characters);
  builder.RegisterService(&state->solves);
  builder.SetMaxReceiveMessageSize(o.max_receive_message_bytes);
  // gRPC sets SO_REUSEPORT by default: a second server on a taken port would start and take half the
  // connections. Without it, a taken port fails here.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  std::vector<std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface>> interceptors;
  interceptors.push_back(MakeReflectionGuard(state->auth));
  interceptors.push_back(MakeWatchLimit());
  builder.experimental().SetInterceptorCreators(std::move(interceptors));
  state->server = builder.BuildAndStart();
  if (!state->server) {
    Invalid(fmt::format("--listen {}: cannot listen there (the port is taken, or the host is not this machine's)",
                        fmt::join(o.listen, ", ")));
  }
  for (size_t i = 0; i < o.listen.size(); ++i) {
    if (ports[i] == 0) {
      Invalid("--listen " + o.listen[i] + ": cannot listen there (the port is taken, or the host is not this "
              "machine's)");
    }
    state->addresses.push_back(HostOf(o.listen[i]) + ":" + std::to_string(ports[i]));
  }
  // Started once the main server is up, so it says SERVING only when the main port does.
  if (!o.health_listen.empty()) state->health = std::make_unique<HealthEndpoint>(o.health_listen);
  std::unique_ptr<Server> server(new Server(std::move(state)));
  if (!o.metrics_listen.empty()) {
    Server* self = server.get();
    server->state_->metrics_endpoint =
        std::make_unique<MetricsEndpoint>(o.metrics_listen, [self] { return self->MetricsText(); });
  }

  const TokenAuthenticator& auth = server->state_->auth;
  spdlog::info("springblend-server {} serving on {} with {} solver threads, cache {}", SPRINGBLEND_VERSION,
               o.listen.empty() ? std::string("no port (in-process only)")
                                : fmt::format("{}", fmt::join(server->addresses(), ", ")),
               o.workers, o.cache_dir.empty() ? std::string("in memory only") : o.cache_dir);
  spdlog::info("transport: {}; {}", o.tls.cert_file.empty()        ? "plaintext"
                                    : o.tls.client_ca_file.empty() ? "TLS"
                                                                   : "mutual TLS",
               auth.enabled() ? fmt::format("{} accepted tokens", auth.size()) : std::string("no tokens: open"));
  for (const auto& address : o.listen) {
    const std::string host = HostOf(address);
    if (auth.enabled() && o.tls.cert_file.empty() && host != "127.0.0.1" && host != "localhost" && host != "[::1]") {
      spdlog::warn("tokens travel in the clear on {}: add --tls-cert and --tls-key", host);
    }
  }
  return server;
}

Server::Server(std::unique_ptr<State> state) : state_(std::move(state)) {}

Server::~Server() {
  state_->options.drain = std::chrono::milliseconds(0);  // no effect when already shut down
  Shutdown();
  state_->metrics_endpoint.reset();  // its thread renders from the state
}

const std::vector<std::string>& Server::addresses() const { return state_->addresses; }
int Server::metrics_port() const { return state_->metrics_endpoint ? state_->metrics_endpoint->port() : 0; }
int Server::health_port() const { return state_->health ? state_->health->port() : 0; }

std::shared_ptr<grpc::Channel> Server::InProcessChannel(const grpc::ChannelArguments& arguments) {
  return state_->server->InProcessChannel(arguments);
}

void Server::Shutdown() {
  std::call_once(state_->shutdown, [this] {
    // Probes see NOT_SERVING while in-flight calls drain, so balancers stop sending new ones.
    if (auto* health = state_->server->GetHealthCheckService()) health->SetServingStatus(false);
    if (state_->health) state_->health->SetServing(false);
    state_->drain.Set(std::chrono::steady_clock::now() + state_->options.drain);
    state_->server->Shutdown(std::chrono::system_clock::now() + state_->options.drain);
  });
  Wait();
}

void Server::Wait() { state_->server->Wait(); }

ServerStats Server::stats() const {
  ServerStats s;
  s.store = state_->store.stats();
  s.cleanup = state_->cleanup;
  s.workers = state_->pool.threads();
  s.workers_busy = state_->pool.busy();
  s.queue_depth = state_->pool.queue_depth();
  s.request_memory_bytes = state_->memory.used();
  return s;
}

std::string Server::MetricsText() const {
  return state_->metrics.Render([this] {
    const ServerStats s = stats();
    std::string out;
    const auto family = [&out](const char* name, const char* type, const char* help, auto value) {
      out += fmt::format("# HELP {} {}\n# TYPE {} {}\n{} {}\n", name, help, name, type, name, value);
    };
    family("springblend_cache_hits_total", "counter", "Lookups that found the character in memory.", s.store.hits);
    family("springblend_cache_misses_total", "counter", "Lookups that did not find the character in memory.",
           s.store.misses);
    family("springblend_cache_evictions_total", "counter", "Characters dropped from memory for the memory budget.",
           s.store.evictions);
    family("springblend_cache_rebuilds_from_disk_total", "counter",
           "Characters rebuilt from their file in the cache directory.", s.store.rebuilds_from_disk);
    family("springblend_cache_builds_total", "counter", "Rigs built (uploads and rebuilds, failed ones too).",
           s.store.builds);
    family("springblend_cache_corrupt_files_total", "counter", "Cache files refused (bad checksum or id).",
           s.store.corrupt_files);
    family("springblend_cache_paths_loaded_total", "counter",
           "Rebuilds from the cache directory that loaded their target paths from the file.", s.store.paths_loaded);
    family("springblend_cache_upgraded_files_total", "counter", "Cache files rewritten in the current version.",
           s.store.upgraded_files);
    family("springblend_cache_cancelled_builds_total", "counter",
           "Builds stopped (no waiter wanted them, or shutdown).", s.store.cancelled_builds);
    family("springblend_cache_bytes", "gauge", "Memory counted for the characters held.", s.store.bytes);
    family("springblend_cache_characters", "gauge", "Characters held in memory.", s.store.characters);
    family("springblend_cache_open_files", "gauge",
           "Cache files open for characters to read their paths from (at most --max-open-cache-files).",
           OpenPathFiles());
    family("springblend_queue_depth", "gauge", "Jobs waiting in the solve pool's queue.", s.queue_depth);
    family("springblend_workers_busy", "gauge", "Solve pool workers running a job.", s.workers_busy);
    family("springblend_workers", "gauge", "Solve pool workers.", s.workers);
    family("springblend_build_workers", "gauge", "Rig build workers.", s.store.build_threads);
    family("springblend_build_workers_busy", "gauge", "Rig build workers running a build.", s.store.builds_running);
    family("springblend_build_queue_depth", "gauge", "Rig builds waiting for a build worker.", s.store.builds_queued);
    family("springblend_request_memory_bytes", "gauge", "Memory counted for requests in flight.",
           s.request_memory_bytes);
    family("springblend_request_memory_limit_bytes", "gauge", "The request memory limit (--request-memory-mb).",
           state_->memory.limit());
    family("springblend_cache_write_failures_total", "counter", "Cache files that could not be written.",
           s.store.write_failures);
    return out;
  });
}

}  // namespace springblend::server
