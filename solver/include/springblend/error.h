// Errors raised by the solver library. One enum says what kind of problem it is, so every front end
// (the CLI's exit codes, the server's gRPC status mapping) decides from the kind, never from the text.
#pragma once

#include <stdexcept>
#include <string>

namespace springblend {

enum class ErrorCode {
  kInvalidInput,  // a mesh, weight vector or option that cannot be used; the message names the culprit
  kNotFound,      // a named thing (file, target, character) does not exist
  kNumerical,     // the solve broke down (non-finite values, a factorization that failed)
  kInternal,      // a bug in springblend
  kCancelled,     // the caller's stop check said stop (a cancelled request, a deadline, a shutdown)
};

const char* ToString(ErrorCode code);

class Error : public std::runtime_error {
 public:
  Error(ErrorCode code, const std::string& message) : std::runtime_error(message), code_(code) {}
  ErrorCode code() const { return code_; }

 private:
  ErrorCode code_;
};

// Data the solver reads back from a file it was given (a cache file's target paths) could not be read: the file
// was cut short, or failed, after it was opened. Its code is kInternal, what every front end answers for it; a
// holder of the rig (the server's store) also knows by the type that the rig is damaged, not the request, and
// drops it so that it is built anew.
class DataLossError : public Error {
 public:
  explicit DataLossError(const std::string& message) : Error(ErrorCode::kInternal, message) {}
};

}  // namespace springblend
