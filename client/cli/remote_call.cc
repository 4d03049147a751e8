#include "remote_call.h"

#include <fmt/format.h>

#include <cstdlib>
#include <string>
#include <vector>
#include <fstream>
#include <iostream>
#include <sstream>

#include "commands.h"
#include "springblend/error.h"

namespace springblend::cli {
namespace {

// "No deadline" for the C++ client, whose ClientOptions::timeout is a duration added to now(): ten years, far beyond
// any upload or bake, and far from overflowing system_clock's nanoseconds.
constexpr std::chrono::milliseconds kNoDeadline = std::chrono::hours(24 * 365 * 10);

// The quick calls' limits when --timeout is not given.
constexpr double kQuickCallSeconds = 60.0;
constexpr double kHealthSeconds = 5.0;

std::string ReadPem(const char* flag, const std::string& path) {
  if (path.empty()) return "";
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(ErrorCode::kInvalidInput, fmt::format("{}: cannot open {}", flag, path));
  std::ostringstream text;
  text << in.rdbuf();
  if (text.str().find("-----BEGIN ") == std::string::npos) {
    throw Error(ErrorCode::kInvalidInput, fmt::format("{}: {} is not a PEM file", flag, path));
  }
  return text.str();
}

bool UsesTls(const Connection& c) { return c.tls || !c.tls_ca.empty() || !c.tls_cert.empty() || !c.tls_key.empty(); }

bool Contains(const std::string& text, const char* part) { return text.find(part) != std::string::npos; }

std::string Seconds(double seconds) { return fmt::format("{:g} s", seconds); }

}  // namespace

Address ResolveAddress(const Connection& connection) {
  if (!connection.server.empty()) return {connection.server, "--server"};
  const char* variable = std::getenv(kServerVariable);
  if (variable != nullptr && *variable != '\0') return {variable, fmt::format("${}", kServerVariable)};
  return {kDefaultServer, "the default"};
}

std::optional<std::chrono::milliseconds> CommandDeadline(const std::string& command, const Connection& connection) {
  double seconds = connection.timeout_seconds;
  if (seconds <= 0.0) {
    if (command == "upload" || command == "solve" || command == "bake-rig") return std::nullopt;
    seconds = command == "health" ? kHealthSeconds : kQuickCallSeconds;
  }
  return std::chrono::milliseconds(static_cast<std::int64_t>(seconds * 1000.0 + 0.5));
}

std::shared_ptr<grpc::Channel> OpenChannel(const Connection& connection) {
  grpc::ChannelArguments arguments;
  arguments.SetMaxReceiveMessageSize(256 << 20);
  const std::string address = ResolveAddress(connection).address;
  if (!UsesTls(connection)) {
    return grpc::CreateCustomChannel(address, grpc::InsecureChannelCredentials(), arguments);
  }
  if (connection.tls_cert.empty() != connection.tls_key.empty()) {
    throw Error(ErrorCode::kInvalidInput,
                "--tls-cert and --tls-key go together (the client certificate "
                "and its key)");
  }
  grpc::SslCredentialsOptions ssl;
  ssl.pem_root_certs = ReadPem("--tls-ca", connection.tls_ca);
  ssl.pem_cert_chain = ReadPem("--tls-cert", connection.tls_cert);
  ssl.pem_private_key = ReadPem("--tls-key", connection.tls_key);
  if (!connection.tls_server_name.empty()) arguments.SetSslTargetNameOverride(connection.tls_server_name);
  return grpc::CreateCustomChannel(address, grpc::SslCredentials(ssl), arguments);
}

ClientOptions CallOptions(const std::string& command, const Connection& connection) {
  ClientOptions options;
  options.address = ResolveAddress(connection).address;
  options.timeout = CommandDeadline(command, connection).value_or(kNoDeadline);
  options.token = connection.token;
  return options;
}

CallFailure Explain(const std::string& command, const CallError& error, const Connection& connection) {
  const std::string& call = error.call();
  const auto code = static_cast<grpc::StatusCode>(error.code());
  const Address where = ResolveAddress(connection);
  const std::string detail = error.what();
  std::string headline = detail, hint;
  switch (code) {
    case grpc::StatusCode::DEADLINE_EXCEEDED: {
      const auto limit = CommandDeadline(command, connection);
      const double seconds = limit ? limit->count() / 1000.0 : 0.0;
      if (connection.timeout_seconds > 0.0) {
        headline = fmt::format("{} did not finish within --timeout {}", call, Seconds(seconds));
        hint = command == "upload" || command == "solve" ? fmt::format(
                                                               "raise --timeout, or leave it out: {} has no "
                                                               "time limit by default",
                                                               command)
                                                         : "raise --timeout; a busy or distant server may need longer";
      } else {
        headline =
            fmt::format("{} did not finish within {} (the default limit of {})", call, Seconds(seconds), command);
        hint =
            "pass --timeout SECONDS to wait longer; a server that never "
            "answers may be behind a firewall";
      }
      if (detail != "Deadline Exceeded") headline += fmt::format(" ({})", detail);
      break;
    }
    case grpc::StatusCode::UNAVAILABLE:
      if (Contains(detail, "shutting down")) {
        hint = "retry: behind a load balancer the call goes to another replica";
        break;
      }
      headline = fmt::format("cannot reach a springblend server at {} ({}): {}", where.address, where.source, detail);
      if (UsesTls(connection) && (Contains(detail, "SSL") || Contains(detail, "ssl") || Contains(detail, "handshake") ||
                                  Contains(detail, "certificate"))) {
        hint =
            "the TLS handshake failed: --tls-ca must name the CA that signed "
            "the server's certificate, "
            "--tls-server-name a name it carries, and a server requiring "
            "client certificates needs --tls-cert "
            "and --tls-key";
      } else if (UsesTls(connection)) {
        hint =
            "is the server running there, and does it serve TLS? (check "
            "--tls-ca and --tls-server-name too)";
      } else {
        hint = fmt::format(
            "is the server running there? Set the address with --server or ${}; "
            "a server using TLS needs --tls or --tls-ca",
            kServerVariable);
      }
      break;
    case grpc::StatusCode::UNAUTHENTICATED:
      hint = connection.token.empty() ? "the server requires a token: pass "
                                        "--token TOKEN or set $SPRINGBLEND_TOKEN"
                                      : "the server does not accept this token: "
                                        "check --token or $SPRINGBLEND_TOKEN";
      break;
    case grpc::StatusCode::PERMISSION_DENIED:
      hint = fmt::format(
          "this token's role does not allow {}; use a token with "
          "the role named above",
          command);
      break;
    case grpc::StatusCode::NOT_FOUND:
      hint = "springblend list shows the characters the server knows";
      break;
    case grpc::StatusCode::RESOURCE_EXHAUSTED:
      hint = "the server is at the limit named above: retry later, or ask for less";
      break;
    case grpc::StatusCode::UNIMPLEMENTED:
      hint = fmt::format(
          "{} answers but does not serve this call: a health-only "
          "port (--health-address)?",
          where.address);
      break;
    case grpc::StatusCode::INTERNAL:
    case grpc::StatusCode::UNKNOWN:
    case grpc::StatusCode::DATA_LOSS:
      hint = "a failure in the server: its log has the details";
      break;
    default:
      break;
  }
  if (!error.progress().empty()) headline += fmt::format("; {}", error.progress());
  CallFailure failure;
  failure.message = fmt::format("springblend {}: {}: {}", command, StatusName(error.code()), headline);
  if (!hint.empty()) failure.message += "\n  " + hint;
  const bool callers_mistake = code == grpc::StatusCode::INVALID_ARGUMENT || code == grpc::StatusCode::NOT_FOUND ||
                               code == grpc::StatusCode::UNAUTHENTICATED || code == grpc::StatusCode::PERMISSION_DENIED;
  failure.exit_code = callers_mistake ? kExitBadInput : kExitUnavailable;
  return failure;
}

std::string ResolveCharacter(Client& client, const std::string& command, const std::string& given) {
  const bool hex = !given.empty() && given.find_first_not_of("0123456789abcdef") == std::string::npos;
  if (hex && given.size() == 64) return given;
  const std::vector<v1::Character> listed = Call(command + " (list, to find --character)", [&] { return client.List(); });
  std::vector<std::string> by_prefix, by_name;
  for (const v1::Character& c : listed) {
    if (hex && given.size() >= 12 && c.id().compare(0, given.size(), given) == 0) by_prefix.push_back(c.id());
    if (c.name() == given) by_name.push_back(c.id());
  }
  const std::vector<std::string>& found = !by_prefix.empty() ? by_prefix : by_name;
  if (found.size() == 1) return found[0];
  if (found.empty()) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("--character '{}': no character on the server has this {} (give a full id, 12 or "
                            "more of its hex digits, or a name; springblend list shows them)",
                            given, hex && given.size() >= 12 ? "id prefix or name" : "name"));
  }
  std::string ids;
  for (const std::string& id : found) ids += (ids.empty() ? "" : ", ") + id.substr(0, 16);
  throw Error(ErrorCode::kInvalidInput,
              fmt::format("--character '{}' names {} characters ({}): give more of the id", given, found.size(), ids));
}

void AddConnectionFlags(CLI::App* cmd, Connection* connection) {
  cmd->add_option("--server", connection->server,
                  fmt::format("server address host:port (default: ${}, else {})", kServerVariable, kDefaultServer));
  cmd->add_flag("--tls", connection->tls, "use TLS, checking the server against the system's roots");
  cmd->add_option("--tls-ca", connection->tls_ca,
                  "PEM CA bundle to check the server's certificate with (implies --tls)");
  cmd->add_option("--tls-cert", connection->tls_cert, "PEM client certificate, for servers requiring mutual TLS");
  cmd->add_option("--tls-key", connection->tls_key, "PEM private key of --tls-cert");
  cmd->add_option("--tls-server-name", connection->tls_server_name, "name the server's certificate must carry "
                                                                    "(default: the host of --server)");
  cmd->add_option("--token", connection->token, "token sent as 'authorization: Bearer TOKEN'")
      ->envname("SPRINGBLEND_TOKEN");
  const auto limit = CommandDeadline(cmd->get_name(), Connection{});
  cmd->add_option("--timeout", connection->timeout_seconds,
                  limit ? fmt::format("seconds each call may take (default {:g})", limit->count() / 1000.0)
                        : std::string("seconds each call may take (default: no limit)"))
      ->check(CLI::Validator(
          [](std::string& text) {
            char* end = nullptr;
            const double seconds = std::strtod(text.c_str(), &end);
            return end != text.c_str() && *end == '\0' && seconds > 0.0 && seconds < 1e9
                       ? std::string()
                       : fmt::format("seconds, a number above 0 (got '{}')", text);
          },
          "SECONDS"));
}

int RunExplained(const std::string& command, const Connection& connection, const std::function<int()>& run) {
  try {
    return run();
  } catch (const CallError& e) {
    const CallFailure failure = Explain(command, e, connection);
    std::cerr << failure.message << "\n";
    return failure.exit_code;
  } catch (const ClientError& e) {  // refused by the client library before any call
    const CallFailure failure = Explain(command, CallError(command, e), connection);
    std::cerr << failure.message << "\n";
    return failure.exit_code;
  }
}

}  // namespace springblend::cli
