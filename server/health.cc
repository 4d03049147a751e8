#include "health.h"

#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server_builder.h>

#include <chrono>
#include <string>
#include <vector>

#include "springblend/error.h"

namespace springblend::server {
namespace {

// Builder plugins are process-wide: linking the reflection library adds reflection to every server built. This
// option drops them from the health server's builder, so it serves health and nothing else.
class WithoutPlugins final : public grpc::ServerBuilderOption {
 public:
  void UpdateArguments(grpc::ChannelArguments*) override {}
  void UpdatePlugins(std::vector<std::unique_ptr<grpc::ServerBuilderPlugin>>* plugins) override { plugins->clear(); }
};

}  // namespace

HealthEndpoint::HealthEndpoint(const std::string& listen) {
  // gRPC takes a port past 65535 without complaint, so the port is checked here.
  const size_t colon = listen.rfind(':');
  const std::string port = colon == std::string::npos ? "" : listen.substr(colon + 1);
  if (colon == 0 || port.empty() || port.size() > 5 ||
      port.find_first_not_of("0123456789") != std::string::npos || std::stoi(port) > 65535) {
    throw Error(ErrorCode::kInvalidInput, "--health-address " + listen + ": expected HOST:PORT (port 0 to 65535)");
  }
  // The default health service (SERVING for "" until told otherwise) is what a server gets with no service of
  // its own that implements health.
  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  builder.AddListeningPort(listen, grpc::InsecureServerCredentials(), &port_);
  builder.SetOption(std::make_unique<WithoutPlugins>());
  builder.RegisterCallbackGenericService(&unimplemented_);
  server_ = builder.BuildAndStart();
  if (!server_ || port_ == 0 || server_->GetHealthCheckService() == nullptr) {
    throw Error(ErrorCode::kInvalidInput,
                "--health-address " + listen + ": cannot listen there (the port is taken, or the host is not this "
                "machine's)");
  }
}

HealthEndpoint::~HealthEndpoint() {
  server_->Shutdown(std::chrono::system_clock::now());
  server_->Wait();
}

void HealthEndpoint::SetServing(bool serving) { server_->GetHealthCheckService()->SetServingStatus(serving); }

}  // namespace springblend::server
