#include "health.h"

#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server_builder.h>

#include <chrono>
#include <string>
#include <vector>

#include "server.h"
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
  CheckListenAddress(listen, "--health-address");
  // The default health service (SERVING for "" until told otherwise) is what a server gets with no service of
  // its own that implements health.
  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  builder.AddListeningPort(listen, grpc::InsecureServerCredentials(), &port_);
  builder.SetOption(std::make_unique<WithoutPlugins>());
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);  // a taken port fails, as on the main server
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
