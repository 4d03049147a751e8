#include "security.h"

#include <grpcpp/security/server_credentials.h>
#include <openssl/evp.h>

#include <algorithm>
#include <cctype>
#include <fstream>
#include <sstream>

#include "springblend/error.h"
#include "status.h"

namespace springblend::server {
namespace {

std::string ReadPem(const std::string& flag, const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(ErrorCode::kInvalidInput, flag + ": cannot read " + path);
  std::ostringstream text;
  text << in.rdbuf();
  if (text.str().find("-----BEGIN ") == std::string::npos) {
    throw Error(ErrorCode::kInvalidInput, flag + ": " + path + " is not a PEM file");
  }
  return text.str();
}

std::string Sha256(const std::string& bytes) {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  EVP_Digest(bytes.data(), bytes.size(), digest, &length, EVP_sha256(), nullptr);
  return {reinterpret_cast<const char*>(digest), length};
}

const char* Describe(Access access) {
  return access == Access::kWrite ? "upload or delete characters" : "read characters and solve";
}

}  // namespace

std::shared_ptr<grpc::ServerCredentials> MakeServerCredentials(const TlsOptions& options) {
  if (options.cert_file.empty()) {
    if (!options.key_file.empty() || !options.client_ca_file.empty()) {
      throw Error(ErrorCode::kInvalidInput, "--tls-key and --tls-client-ca need --tls-cert");
    }
    return grpc::InsecureServerCredentials();
  }
  if (options.key_file.empty()) throw Error(ErrorCode::kInvalidInput, "--tls-cert needs --tls-key");
  grpc::SslServerCredentialsOptions ssl;
  ssl.pem_key_cert_pairs.push_back(
      {ReadPem("--tls-key", options.key_file), ReadPem("--tls-cert", options.cert_file)});
  if (!options.client_ca_file.empty()) {
    ssl.pem_root_certs = ReadPem("--tls-client-ca", options.client_ca_file);
    ssl.client_certificate_request = GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY;
  }
  return grpc::SslServerCredentials(ssl);
}

void TokenAuthenticator::Add(const std::string& token, Role role, const std::string& where) {
  if (token.empty()) throw Error(ErrorCode::kInvalidInput, "--token: a token may not be empty");
  // A token given twice would keep whichever role came last (a --token full token silently solve-only).
  const auto [at, added] = tokens_.emplace(Sha256(token), Token{role, where});
  if (!added) {
    throw Error(ErrorCode::kInvalidInput, where + ": the token of " + at->second.where +
                                              " again: refusing to start (each token once, with one role)");
  }
}

void TokenAuthenticator::AddFile(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error(ErrorCode::kInvalidInput, "--tokens-file: cannot read " + path);
  std::string line;
  int found = 0;
  for (int number = 1; std::getline(in, line); ++number) {
    std::istringstream words(line);
    std::string role, token, extra;
    words >> role >> token >> extra;
    if (role.empty() || role[0] == '#') continue;
    const std::string where = "--tokens-file " + path + ":" + std::to_string(number);
    if (token.empty() || !extra.empty()) {
      throw Error(ErrorCode::kInvalidInput, where + ": expected 'ROLE TOKEN' (ROLE is full or solve)");
    }
    ++found;
    if (role == "full") {
      Add(token, Role::kFull, where);
    } else if (role == "solve") {
      Add(token, Role::kSolve, where);
    } else {
      throw Error(ErrorCode::kInvalidInput, where + ": unknown role '" + role + "' (full or solve)");
    }
  }
  // An empty secret mount (or a file of comments) must not silently turn authentication off.
  if (found == 0) {
    throw Error(ErrorCode::kInvalidInput, "--tokens-file " + path +
                                              " has no tokens: refusing to start with authentication off; omit "
                                              "--tokens-file to run open");
  }
}

AuthVerdict TokenAuthenticator::Check(const grpc::ServerContextBase& call, Access needed) const {
  return Check(call.client_metadata(), needed);
}

AuthVerdict TokenAuthenticator::Check(const std::multimap<grpc::string_ref, grpc::string_ref>& metadata,
                                      Access needed) const {
  using Kind = AuthVerdict::Kind;
  if (tokens_.empty()) return {};
  const auto header = metadata.find(kAuthorizationHeader);
  if (header == metadata.end()) {
    return {Kind::kMissing, "this server needs a token: send the metadata header 'authorization: Bearer TOKEN'"};
  }
  const std::string value(header->second.data(), header->second.size());
  // The scheme is case-insensitive (RFC 9110 section 11.1): bearer, BEARER and Bearer alike.
  constexpr std::string_view kBearer = "bearer ";
  const bool bearer = value.size() >= kBearer.size() &&
                      std::equal(kBearer.begin(), kBearer.end(), value.begin(), [](char a, char b) {
                        return a == std::tolower(static_cast<unsigned char>(b));
                      });
  if (!bearer) return {Kind::kMissing, "the authorization header must read 'Bearer TOKEN'"};
  const auto known = tokens_.find(Sha256(value.substr(kBearer.size())));
  if (known == tokens_.end()) return {Kind::kUnknown, "the token is not one this server accepts"};
  if (needed == Access::kWrite && known->second.role != Role::kFull) {
    return {Kind::kForbidden, std::string("this token may not ") + Describe(needed) + "; it needs the full role"};
  }
  return {};
}

namespace {

// Cancels a reflection call at once when its metadata carries no accepted token.
class ReflectionGuard final : public grpc::experimental::Interceptor {
 public:
  ReflectionGuard(grpc::experimental::ServerRpcInfo* info, const TokenAuthenticator& auth) : info_(info), auth_(auth) {}
  void Intercept(grpc::experimental::InterceptorBatchMethods* methods) override {
    if (methods->QueryInterceptionHookPoint(grpc::experimental::InterceptionHookPoints::POST_RECV_INITIAL_METADATA)) {
      const auto* metadata = methods->GetRecvInitialMetadata();
      // Refused with the verdict's status (UNAUTHENTICATED, PERMISSION_DENIED), as every other method is.
      if (metadata == nullptr) {
        CancelCall(info_->server_context(), ToStatus(AuthVerdict{AuthVerdict::Kind::kMissing, "no metadata"}));
      } else if (const AuthVerdict verdict = auth_.Check(*metadata, Access::kRead); !verdict.allowed()) {
        CancelCall(info_->server_context(), ToStatus(verdict));
      }
    }
    methods->Proceed();
  }

 private:
  grpc::experimental::ServerRpcInfo* info_;
  const TokenAuthenticator& auth_;
};

class ReflectionGuardFactory final : public grpc::experimental::ServerInterceptorFactoryInterface {
 public:
  explicit ReflectionGuardFactory(const TokenAuthenticator& auth) : auth_(auth) {}
  grpc::experimental::Interceptor* CreateServerInterceptor(grpc::experimental::ServerRpcInfo* info) override {
    if (!auth_.enabled() || std::string_view(info->method()).rfind("/grpc.reflection.", 0) != 0) return nullptr;
    return new ReflectionGuard(info, auth_);
  }

 private:
  const TokenAuthenticator& auth_;
};

}  // namespace

std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> MakeReflectionGuard(
    const TokenAuthenticator& auth) {
  return std::make_unique<ReflectionGuardFactory>(auth);
}

}  // namespace springblend::server
