// Transport security and tokens, end to end: a CA, server and client certificates made with the openssl
// command at test time, a real server process, and the C++ client library and the CLI.
#include <gmock/gmock.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <array>
#include <cstdio>
#include <cstdlib>
#include <memory>

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
}

}  // namespace
}  // namespace springblend
