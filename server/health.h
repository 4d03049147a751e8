// A plaintext endpoint that serves only the standard health service (grpc.health.v1.Health), for probes that
// cannot speak TLS (the kubelet's gRPC probe, grpc_health_probe without -tls) when the main port serves TLS.
// It is a gRPC server of its own with nothing else registered, not even reflection: every other call there
// is UNIMPLEMENTED. It reports what the main server reports: main sets it NOT_SERVING when draining starts.
#pragma once

#include <grpcpp/generic/async_generic_service.h>
#include <grpcpp/server.h>
#include <grpcpp/support/server_interceptor.h>

#include <memory>
#include <string>

namespace springblend::server {

// Health's Watch streams need no token (probes use them), but each holds a call open for as long as its client
// likes (2,000 held 36 MiB): at most this many at once per server; one more is refused at once with
// RESOURCE_EXHAUSTED. Check calls are never limited.
inline constexpr int kMaxHealthWatches = 100;
std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> MakeWatchLimit(int limit = kMaxHealthWatches);

class HealthEndpoint {
 public:
  // Listens on `listen` (HOST:PORT; port 0 picks a free one) and reports SERVING. Throws Error(kInvalidInput)
  // naming --health-address when it cannot listen there.
  explicit HealthEndpoint(const std::string& listen);
  ~HealthEndpoint();  // stops at once (probes do not wait to be drained)
  int port() const { return port_; }
  // SERVING or NOT_SERVING, for the overall status ("") and every service name.
  void SetServing(bool serving);

 private:
  // Answers every method but health with UNIMPLEMENTED; a server with no method of its own would not start.
  grpc::CallbackGenericService unimplemented_;
  std::unique_ptr<grpc::Server> server_;
  int port_ = 0;
};

}  // namespace springblend::server
