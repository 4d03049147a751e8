// Who may reach the server and what they may do: TLS (optionally mutual) on the listening port, and bearer
// tokens, each with a role, checked by every handler before it does any work. The standard health service
// is not ours and stays open, so load balancers and probes need no token.
#pragma once

#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server_context.h>
#include <grpcpp/support/server_interceptor.h>

#include <map>
#include <memory>
#include <string>
#include <vector>

namespace springblend::server {

struct TlsOptions {
  std::string cert_file;       // PEM certificate chain of the server; empty: plaintext
  std::string key_file;        // PEM private key of cert_file
  std::string client_ca_file;  // PEM CA bundle; when set, every client must present a certificate it signed
};

// Plaintext credentials when options.cert_file is empty, TLS otherwise. Throws Error(kInvalidInput) naming
// the flag when a file is missing or unreadable, or when a certificate comes without its key.
std::shared_ptr<grpc::ServerCredentials> MakeServerCredentials(const TlsOptions& options);

// What a call needs: kRead for GetCharacter, ListCharacters, Solve and Interactive; kWrite also for
// UploadCharacter and DeleteCharacter (they change the shared cache).
enum class Access { kRead, kWrite };

// A token's role: "solve" tokens may read and solve, "full" tokens may also upload and delete.
enum class Role { kSolve, kFull };

// The outcome of a token check; status.cc turns it into UNAUTHENTICATED or PERMISSION_DENIED.
struct AuthVerdict {
  enum class Kind { kAllowed, kMissing, kUnknown, kForbidden };
  Kind kind = Kind::kAllowed;
  std::string message;  // why not, for the caller
  bool allowed() const { return kind == Kind::kAllowed; }
};

// The metadata header a client sends its token in: "authorization: Bearer TOKEN".
inline constexpr char kAuthorizationHeader[] = "authorization";

class TokenAuthenticator {
 public:
  // No tokens: every call is allowed (the server is open, as on a trusted network).
  TokenAuthenticator() = default;
  // `where` names the token's origin in messages (the flag, or the file and line). Throws Error(kInvalidInput)
  // naming both origins when the token was added before.
  void Add(const std::string& token, Role role, const std::string& where = "--token");
  // Reads a tokens file: one "ROLE TOKEN" per line (ROLE is full or solve); blank lines and lines starting
  // with # are skipped. Throws Error(kInvalidInput) naming the file and line.
  void AddFile(const std::string& path);
  bool enabled() const { return !tokens_.empty(); }
  size_t size() const { return tokens_.size(); }

  AuthVerdict Check(const grpc::ServerContextBase& call, Access needed) const;
  AuthVerdict Check(const std::multimap<grpc::string_ref, grpc::string_ref>& metadata, Access needed) const;

 private:
  // Keyed by the token's SHA-256, so neither the map's order nor the comparison leaks the token itself.
  struct Token {
    Role role;
    std::string where;  // its origin, for the message when it comes again
  };
  std::map<std::string, Token> tokens_;
};

// Server reflection is gRPC's service, not ours, so its calls pass through no handler of ours: this interceptor
// cancels every reflection call without an accepted token when tokens are configured (only health stays open).
std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> MakeReflectionGuard(
    const TokenAuthenticator& auth);

}  // namespace springblend::server
