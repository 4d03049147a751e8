// How the remote commands reach a server and say what went wrong: the connection flags shared by upload, solve, list,
// delete and health, the channel they open, each command's deadline, and failures turned into a message that names
// the call, the status code (by name) and what to do about it.
#pragma once

#include <grpcpp/grpcpp.h>

#include <CLI/CLI.hpp>

#include <chrono>
#include <functional>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>

#include "springblend/client.h"

namespace springblend::cli {

// The flags every remote command takes.
struct Connection {
  std::string server;  // --server; empty: $SPRINGBLEND_SERVER, else kDefaultServer
  bool tls = false;
  std::string tls_ca, tls_cert, tls_key, tls_server_name, token;
  double timeout_seconds = 0.0;  // --timeout; 0: the command's default (CommandDeadline)
};

inline constexpr char kDefaultServer[] = "127.0.0.1:50051";
inline constexpr char kServerVariable[] = "SPRINGBLEND_SERVER";

// The address to dial and where it came from ("--server", "$SPRINGBLEND_SERVER" or "the default").
struct Address {
  std::string address;
  std::string source;
};
Address ResolveAddress(const Connection& connection);

// The deadline of each call a command makes: --timeout when given; otherwise none for upload, solve and bake-rig
// (they take as long as the rig or the frames take: minutes for a face), and a few seconds for the quick calls, so a
// script never hangs on a black-holed address.
std::optional<std::chrono::milliseconds> CommandDeadline(const std::string& command, const Connection& connection);

// A channel to the resolved address with the TLS flags. Bad TLS flags (a file that is not PEM, --tls-cert without
// --tls-key) throw Error(kInvalidInput) naming the flag and the file.
std::shared_ptr<grpc::Channel> OpenChannel(const Connection& connection);

// ClientOptions for Client(channel, options): the token and the command's deadline.
ClientOptions CallOptions(const std::string& command, const Connection& connection);


// A failed call, with what the CLI prints: "springblend upload: DEADLINE_EXCEEDED: ..." and a hint.
struct CallFailure {
  std::string message;  // one or two lines for stderr, without a trailing newline
  int exit_code;        // kExitBadInput for the caller's mistakes, kExitUnavailable for the server's state
};
// A ClientError from one call of a command, carrying which call it was ("upload", "get", "solve") and how far it got
// ("12 of 36 frames arrived"; may be empty).
class CallError : public ClientError {
 public:
  CallError(std::string call, const ClientError& error, std::string progress = "")
      : ClientError(error), call_(std::move(call)), progress_(std::move(progress)) {}
  const std::string& call() const { return call_; }
  const std::string& progress() const { return progress_; }

 private:
  std::string call_, progress_;
};

CallFailure Explain(const std::string& command, const CallError& error, const Connection& connection);

// Runs one call of a command; its ClientError becomes a CallError naming `call`.
template <class F>
auto Call(const std::string& call, F&& run) -> decltype(run()) {
  try {
    return run();
  } catch (const CallError&) {
    throw;
  } catch (const ClientError& e) {
    throw CallError(call, e);
  }
}

// --character as people give it: a full id, a prefix of 12 or more of its hex digits (as the logs and `list`
// show them), or a character's name; a prefix or name must name exactly one character the server lists.
std::string ResolveCharacter(Client& client, const std::string& command, const std::string& given);

// The connection flags of a remote command (--server, the TLS flags, --token, --timeout with the command's
// default deadline in its help), filling *connection.
void AddConnectionFlags(CLI::App* cmd, Connection* connection);

// Runs a remote command; a failed call (CallError) or a request the client library refused (ClientError) becomes
// the message Explain gives, on stderr, and its exit code.
int RunExplained(const std::string& command, const Connection& connection, const std::function<int()>& run);

}  // namespace springblend::cli
