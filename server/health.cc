#include "health.h"

#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server_builder.h>

#include <fmt/format.h>

#include <atomic>
#include <chrono>
#include <string>
#include <vector>

#include "server.h"
#include "springblend/error.h"
#include "status.h"

namespace springblend::server {
namespace {

// Builder plugins are process-wide: linking the reflection library adds reflection to every server built. This
// option drops them from the health server's builder, so it serves health and nothing else.
class WithoutPlugins final : public grpc::ServerBuilderOption {
 public:
  void UpdateArguments(grpc::ChannelArguments*) override {}
  void UpdatePlugins(std::vector<std::unique_ptr<grpc::ServerBuilderPlugin>>* plugins) override { plugins->clear(); }
};

// Counts the Watch streams open (an interceptor lives as long as its call) and cancels those past the limit.
class WatchLimit final : public grpc::experimental::Interceptor {
 public:
  WatchLimit(grpc::experimental::ServerRpcInfo* info, std::shared_ptr<std::atomic<int>> open, int limit)
      : info_(info), open_(std::move(open)), admitted_(open_->fetch_add(1) < limit), limit_(limit) {}
  ~WatchLimit() override { open_->fetch_sub(1); }
  void Intercept(grpc::experimental::InterceptorBatchMethods* methods) override {
    if (!admitted_ &&
        methods->QueryInterceptionHookPoint(grpc::experimental::InterceptionHookPoints::POST_RECV_INITIAL_METADATA)) {
      CancelCall(info_->server_context(),
                 ToStatus(LimitError(fmt::format("this server already has {} health Watch streams open (the most it keeps); "
                                         "use Check, or close a Watch",
                                         limit_))));
    }
    methods->Proceed();
  }

 private:
  grpc::experimental::ServerRpcInfo* info_;
  std::shared_ptr<std::atomic<int>> open_;
  const bool admitted_;
  const int limit_;
};

class WatchLimitFactory final : public grpc::experimental::ServerInterceptorFactoryInterface {
 public:
  explicit WatchLimitFactory(int limit) : limit_(limit) {}
  grpc::experimental::Interceptor* CreateServerInterceptor(grpc::experimental::ServerRpcInfo* info) override {
    if (std::string_view(info->method()) != "/grpc.health.v1.Health/Watch") return nullptr;
    return new WatchLimit(info, open_, limit_);
  }

 private:
  const int limit_;
  std::shared_ptr<std::atomic<int>> open_ = std::make_shared<std::atomic<int>>(0);
};

}  // namespace

std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> MakeWatchLimit(int limit) {
  return std::make_unique<WatchLimitFactory>(limit);
}

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
  std::vector<std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface>> interceptors;
  interceptors.push_back(MakeWatchLimit());
  builder.experimental().SetInterceptorCreators(std::move(interceptors));
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
