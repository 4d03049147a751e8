// Transport security and tokens, end to end: a CA, server and client certificates made with the openssl
// command at test time, a real server process, and the C++ client library and the CLI.
#include <gmock/gmock.h>
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <array>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <future>
#include <memory>
#include <sstream>
#include <thread>

#include "grpc/health/v1/health.grpc.pb.h"
#include "integration/server_process.h"
#include "springblend/client.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using testing::CylinderRig;
using testing::MessageOf;
using testing::ServerProcess;
using testing::StatusOf;
using testing::SweepRequest;
using testing::TempDir;

bool Run(const std::string& command) {
  const bool ok = std::system((command + " >/dev/null 2>&1").c_str()) == 0;
  if (!ok) std::cerr << "failed: " << command << "\n";
  return ok;
}

// A CA, a server certificate for localhost and 127.0.0.1, a client certificate from the same CA, and a client
// certificate from a CA the server does not know. P-256 keys: quick to make.
class Certificates {
 public:
  Certificates() {
    const std::string key = "-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes";
    MakeCa("ca", "springblend test CA");
    MakeCa("rogue-ca", "another CA");
    Issue("server", "ca", "localhost", key, "subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth");
    Issue("client", "ca", "a trusted artist", key, "extendedKeyUsage=clientAuth");
    Issue("rogue", "rogue-ca", "a stranger", key, "extendedKeyUsage=clientAuth");
  }
  std::string File(const std::string& name) const { return dir_.File(name); }
  bool ok() const { return ok_; }

 private:
  void MakeCa(const std::string& name, const std::string& subject) {
    ok_ = ok_ && Run(("openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days 2 -subj '/CN=" +
            subject + "' -addext basicConstraints=critical,CA:TRUE -addext keyUsage=critical,keyCertSign,cRLSign"
            " -keyout " + File(name + ".key") + " -out " + File(name + ".pem")));
  }
  void Issue(const std::string& name, const std::string& ca, const std::string& subject, const std::string& key,
             const std::string& extensions) {
    const std::string ext = dir_.Write(name + ".ext", "basicConstraints=CA:FALSE\n" + extensions + "\n");
    ok_ = ok_ && Run(("openssl req -new " + key + " -subj '/CN=" + subject + "' -keyout " + File(name + ".key") +
            " -out " + File(name + ".csr")));
    ok_ = ok_ && Run(("openssl x509 -req -days 2 -in " + File(name + ".csr") + " -CA " + File(ca + ".pem") + " -CAkey " +
            File(ca + ".key") + " -CAcreateserial -extfile " + ext + " -out " + File(name + ".pem")));
  }
  TempDir dir_;
  bool ok_ = true;
};

using HealthStatus = grpc::health::v1::HealthCheckResponse;

// Health.Check for the whole server (service ""), as a plaintext probe asks it (the kubelet's, or
// grpc_health_probe without -tls). `status` says whether the call itself worked.
HealthStatus::ServingStatus ProbeHealth(const std::string& address, grpc::Status* status) {
  auto stub = grpc::health::v1::Health::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(5));
  grpc::health::v1::HealthCheckRequest request;
  HealthStatus response;
  *status = stub->Check(&context, request, &response);
  return response.status();
}

// One server reflection request (list the services) as a unary call: OK where reflection is served, UNIMPLEMENTED
// where it is not.
grpc::StatusCode CallReflection(const std::shared_ptr<grpc::Channel>& channel) {
  grpc::GenericStub stub(channel);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(5));
  grpc::Slice list_services(std::string("\x3a\x01*", 3));  // ServerReflectionRequest{list_services: "*"}
  grpc::ByteBuffer request(&list_services, 1), response;
  std::promise<grpc::Status> done;
  stub.UnaryCall(&context, "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo", grpc::StubOptions(),
                 &request, &response, [&done](grpc::Status status) { done.set_value(std::move(status)); });
  return done.get_future().get().error_code();
}

class SecurityTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() { certificates_ = new Certificates(); }
  static void TearDownTestSuite() {
    delete certificates_;
    certificates_ = nullptr;
  }
  static std::string File(const std::string& name) { return certificates_->File(name); }
  // A failure here fails every test (a failure in SetUpTestSuite would only skip them).
  void SetUp() override { ASSERT_TRUE(certificates_->ok()) << "openssl could not make the test certificates"; }

  std::unique_ptr<ServerProcess> StartServer(std::vector<std::string> flags) {
    auto server = std::make_unique<ServerProcess>(cache_.path().string(), flags);
    EXPECT_FALSE(server->address().empty()) << "the server did not start";
    return server;
  }
  static std::shared_ptr<grpc::Channel> TlsChannel(const std::string& address) {
    std::ifstream in(File("ca.pem"));
    std::stringstream ca;
    ca << in.rdbuf();
    grpc::SslCredentialsOptions ssl;
    ssl.pem_root_certs = ca.str();
    return grpc::CreateChannel(address, grpc::SslCredentials(ssl));
  }
  ClientOptions Tls(const std::string& address) const {
    ClientOptions options{address, std::chrono::seconds(20)};
    options.tls_root_ca_file = File("ca.pem");
    return options;
  }

  static inline Certificates* certificates_ = nullptr;
  TempDir cache_;
};

TEST_F(SecurityTest, ATlsClientTrustingTheCaIsServed) {
  auto server = StartServer({"--tls-cert", File("server.pem"), "--tls-key", File("server.key")});
  Client client(Tls(server->address()));
  EXPECT_TRUE(client.Healthy());
  CylinderRig cylinder;
  const v1::Character c = client.Upload(cylinder.rest, cylinder.targets);
  EXPECT_EQ(client.Solve(SweepRequest(c.id(), 2, {0.5, 0.5}), [](const v1::SolvedFrame&) {}), 2);
  // The certificate names localhost too.
  ClientOptions by_name = Tls(server->address());
  by_name.tls_server_name = "localhost";
  EXPECT_EQ(Client(by_name).List().size(), 1u);
}

TEST_F(SecurityTest, APlaintextOrUntrustingClientCannotTalkToATlsServer) {
  auto server = StartServer({"--tls-cert", File("server.pem"), "--tls-key", File("server.key")});
  Client plaintext({server->address(), std::chrono::seconds(5)});
  EXPECT_EQ(StatusOf([&] { plaintext.List(); }), grpc::StatusCode::UNAVAILABLE);
  EXPECT_FALSE(plaintext.Healthy());
  // TLS, but checking against another CA.
  ClientOptions wrong_ca = Tls(server->address());
  wrong_ca.tls_root_ca_file = File("rogue-ca.pem");
  wrong_ca.timeout = std::chrono::seconds(5);
  EXPECT_EQ(StatusOf([&] { Client(wrong_ca).List(); }), grpc::StatusCode::UNAVAILABLE);
  // A name the certificate does not carry.
  ClientOptions wrong_name = Tls(server->address());
  wrong_name.tls_server_name = "elsewhere.example";
  wrong_name.timeout = std::chrono::seconds(5);
  EXPECT_EQ(StatusOf([&] { Client(wrong_name).List(); }), grpc::StatusCode::UNAVAILABLE);
}

TEST_F(SecurityTest, MutualTlsRefusesClientsWithoutACertificateFromItsCa) {
  auto server = StartServer({"--tls-cert", File("server.pem"), "--tls-key", File("server.key"), "--tls-client-ca",
                             File("ca.pem")});
  ClientOptions anonymous = Tls(server->address());
  anonymous.timeout = std::chrono::seconds(5);
  EXPECT_EQ(StatusOf([&] { Client(anonymous).List(); }), grpc::StatusCode::UNAVAILABLE);

  ClientOptions stranger = anonymous;
  stranger.tls_cert_file = File("rogue.pem");
  stranger.tls_key_file = File("rogue.key");
  EXPECT_EQ(StatusOf([&] { Client(stranger).List(); }), grpc::StatusCode::UNAVAILABLE);

  ClientOptions trusted = Tls(server->address());
  trusted.tls_cert_file = File("client.pem");
  trusted.tls_key_file = File("client.key");
  Client client(trusted);
  EXPECT_TRUE(client.Healthy());
  EXPECT_TRUE(client.List().empty());
}

TEST_F(SecurityTest, TokensGiveUnauthenticatedAndPermissionDeniedAndHealthStaysOpen) {
  TempDir config;
  const std::string tokens = config.Write("tokens", "# role token\nfull alpha-secret\n\nsolve beta-secret\n");
  auto server = StartServer({"--tokens-file", tokens, "--token", "gamma-secret"});
  ClientOptions base{server->address(), std::chrono::seconds(20)};
  Client anonymous(base);
  EXPECT_TRUE(anonymous.Healthy()) << "health needs no token";
  EXPECT_EQ(StatusOf([&] { anonymous.List(); }), grpc::StatusCode::UNAUTHENTICATED);
  EXPECT_THAT(MessageOf([&] { anonymous.List(); }), HasSubstr("authorization: Bearer TOKEN"));

  ClientOptions wrong = base;
  wrong.token = "alpha-secret-not";
  EXPECT_EQ(StatusOf([&] { Client(wrong).List(); }), grpc::StatusCode::UNAUTHENTICATED);

  ClientOptions full = base, solve = base, flag = base;
  full.token = "alpha-secret";
  solve.token = "beta-secret";
  flag.token = "gamma-secret";
  CylinderRig cylinder;
  EXPECT_EQ(StatusOf([&] { Client(solve).Upload(cylinder.rest, cylinder.targets); }),
            grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_THAT(MessageOf([&] { Client(solve).Upload(cylinder.rest, cylinder.targets); }), HasSubstr("full role"));
  EXPECT_EQ(StatusOf([&] { anonymous.Upload(cylinder.rest, cylinder.targets); }), grpc::StatusCode::UNAUTHENTICATED);
  const v1::Character c = Client(full).Upload(cylinder.rest, cylinder.targets);

  Client solver(solve);
  EXPECT_EQ(solver.List().size(), 1u);
  EXPECT_EQ(solver.Get(c.id()).id(), c.id());
  EXPECT_EQ(solver.Solve(SweepRequest(c.id(), 2, {0.5, 0.5}), [](const v1::SolvedFrame&) {}), 2);
  EXPECT_EQ(StatusOf([&] { anonymous.Solve(SweepRequest(c.id(), 2, {0.5, 0.5}), [](const v1::SolvedFrame&) {}); }),
            grpc::StatusCode::UNAUTHENTICATED);
  EXPECT_EQ(StatusOf([&] { solver.Delete(c.id()); }), grpc::StatusCode::PERMISSION_DENIED);

  // An interactive session without a token ends at once, refused.
  v1::InteractiveStart start;
  start.set_character_id(c.id());
  auto session = anonymous.StartInteractive(start);
  session->Close();
  v1::SolvedFrame frame;
  while (session->Next(&frame)) {
  }
  EXPECT_EQ(StatusOf([&] { session->Finish(); }), grpc::StatusCode::UNAUTHENTICATED);

  Client(flag).Delete(c.id());  // a --token token has the full role
  EXPECT_TRUE(Client(full).List().empty());
}

#ifdef SPRINGBLEND_CLI  // built with the CLI (SPRINGBLEND_BUILD_CLI, on but in .ci/run's ASan stage)
TEST_F(SecurityTest, TlsAndTokensTogetherThroughTheCli) {
  TempDir config;
  const std::string tokens = config.Write("tokens", "solve cli-secret\n");
  auto server = StartServer({"--tls-cert", File("server.pem"), "--tls-key", File("server.key"), "--tls-client-ca",
                             File("ca.pem"), "--tokens-file", tokens});
  const std::string base = std::string(SPRINGBLEND_CLI) + " list --server " + server->address() + " --tls-ca " +
                           File("ca.pem") + " --tls-cert " + File("client.pem") + " --tls-key " + File("client.key");
  auto exit_code = [](const std::string& command) {
    const int status = std::system((command + " >/dev/null 2>&1").c_str());
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  };
  EXPECT_EQ(exit_code(base + " --token cli-secret"), 0);
  EXPECT_EQ(exit_code("SPRINGBLEND_TOKEN=cli-secret " + base), 0);
  EXPECT_EQ(exit_code(base), 2) << "no token: the caller's mistake";
  EXPECT_EQ(exit_code(std::string(SPRINGBLEND_CLI) + " list --server " + server->address() + " --token cli-secret"), 4)
      << "plaintext to a TLS server: unavailable";
}
#endif

TEST_F(SecurityTest, APlaintextHealthAddressBesideTlsServesHealthAndNothingElse) {
  auto server = StartServer({"--tls-cert", File("server.pem"), "--tls-key", File("server.key"), "--health-address",
                             "127.0.0.1:0", "--workers", "1", "--drain-seconds", "20"});
  const std::string health = server->health_address();
  ASSERT_FALSE(health.empty()) << "no 'health on' line";
  ASSERT_NE(health, server->address());

  // A plaintext probe gets SERVING there...
  grpc::Status status;
  EXPECT_EQ(ProbeHealth(health, &status), HealthStatus::SERVING);
  EXPECT_TRUE(status.ok()) << status.error_message();
  Client probe({health, std::chrono::seconds(5)});
  EXPECT_TRUE(probe.Healthy());
  // ...and nothing else: no characters, no solves, no reflection.
  CylinderRig cylinder;
  EXPECT_EQ(StatusOf([&] { probe.List(); }), grpc::StatusCode::UNIMPLEMENTED);
  EXPECT_EQ(StatusOf([&] { probe.Upload(cylinder.rest, cylinder.targets); }), grpc::StatusCode::UNIMPLEMENTED);
  EXPECT_EQ(StatusOf([&] { probe.Solve(SweepRequest(std::string(64, 'a'), 1, {0.5, 0.5}), [](const v1::SolvedFrame&) {}); }),
            grpc::StatusCode::UNIMPLEMENTED);
  EXPECT_EQ(CallReflection(grpc::CreateChannel(health, grpc::InsecureChannelCredentials())),
            grpc::StatusCode::UNIMPLEMENTED);
  EXPECT_EQ(CallReflection(TlsChannel(server->address())), grpc::StatusCode::OK) << "reflection on the main port";

  // The main port still demands TLS, health included.
  Client plaintext({server->address(), std::chrono::seconds(5)});
  EXPECT_FALSE(plaintext.Healthy());
  EXPECT_EQ(StatusOf([&] { plaintext.List(); }), grpc::StatusCode::UNAVAILABLE);
  EXPECT_NE(ProbeHealth(server->address(), &status), HealthStatus::SERVING);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::UNAVAILABLE);
  Client client(Tls(server->address()));
  EXPECT_TRUE(client.Healthy());

  // SIGTERM while a solve streams: the server drains it, and the health address says NOT_SERVING meanwhile.
  const v1::Character c = client.Upload(cylinder.rest, cylinder.targets);
  auto stub = v1::SolveService::NewStub(TlsChannel(server->address()));
  grpc::ClientContext context;
  auto reader = stub->Solve(&context, SweepRequest(c.id(), 2000, {1, 1}));
  v1::SolvedFrame frame;
  ASSERT_TRUE(reader->Read(&frame));
  ASSERT_EQ(kill(server->pid(), SIGTERM), 0);
  HealthStatus::ServingStatus seen = HealthStatus::SERVING;
  for (int i = 0; i < 50 && seen == HealthStatus::SERVING; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    seen = ProbeHealth(health, &status);
  }
  EXPECT_EQ(seen, HealthStatus::NOT_SERVING);
  EXPECT_TRUE(status.ok()) << status.error_message();
  EXPECT_TRUE(reader->Read(&frame)) << "the stream in flight still drains";
  context.TryCancel();
  while (reader->Read(&frame)) {
  }
  reader->Finish();
  EXPECT_EQ(server->Stop(), 0);
}

TEST(SecurityFlags, BadTlsOrTokenFlagsStopTheServerWithAMessage) {
  TempDir cache, config;
  EXPECT_TRUE(ServerProcess(cache.path().string(), {"--tls-cert", config.Write("cert.pem", "not a certificate")})
                  .address()
                  .empty());
  EXPECT_TRUE(ServerProcess(cache.path().string(), {"--tls-cert", config.File("missing.pem"), "--tls-key",
                                                    config.File("missing.key")})
                  .address()
                  .empty());
  EXPECT_TRUE(
      ServerProcess(cache.path().string(), {"--tokens-file", config.Write("tokens", "superuser x\n")}).address().empty());
  EXPECT_TRUE(ServerProcess(cache.path().string(), {"--health-address", "127.0.0.1:99999"}).address().empty());
  EXPECT_TRUE(ServerProcess(cache.path().string(), {"--health-address", "no-port"}).address().empty());
  // A port another process listens on.
  const int taken = socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t length = sizeof(address);
  ASSERT_EQ(bind(taken, reinterpret_cast<sockaddr*>(&address), sizeof(address)), 0);
  ASSERT_EQ(listen(taken, 1), 0);
  ASSERT_EQ(getsockname(taken, reinterpret_cast<sockaddr*>(&address), &length), 0);
  const std::string in_use = "127.0.0.1:" + std::to_string(ntohs(address.sin_port));
  EXPECT_TRUE(ServerProcess(cache.path().string(), {"--health-address", in_use}).address().empty());
  close(taken);
}

}  // namespace
}  // namespace springblend
