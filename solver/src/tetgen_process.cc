#include "tetgen_process.h"

#include <fcntl.h>
#include <fmt/format.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <mutex>
#include <system_error>
#include <utility>

#include "springblend/error.h"
#include "springblend/runtime.h"

namespace springblend {
namespace {

std::mutex helper_mutex;
std::string helper_override;  // SetTetGenHelper's path; guarded by helper_mutex

}  // namespace

void SetTetGenHelper(const std::string& path) {
  std::lock_guard lock(helper_mutex);
  helper_override = path;
}

namespace internal::tetgen {
namespace {

constexpr const char* kHelperName = "springblend-tetgen";
constexpr const char* kHelperVariable = "SPRINGBLEND_TETGEN_HELPER";

[[noreturn]] void CannotStart(const std::string& reason) {
  throw Error(ErrorCode::kNumerical, "cannot tetrahedralize the surface: TetGen could not be started: " + reason);
}

std::string SystemError(const char* call, int error) {
  return fmt::format("{} failed: {}", call, std::generic_category().message(error));
}

std::string SystemError(const char* call) { return SystemError(call, errno); }

bool IsExecutableFile(const std::string& path) {
  std::error_code error;
  return std::filesystem::is_regular_file(path, error) && access(path.c_str(), X_OK) == 0;
}

// Closes a descriptor when it goes out of scope.
class Descriptor {
 public:
  explicit Descriptor(int fd = -1) : fd_(fd) {}
  Descriptor(const Descriptor&) = delete;
  Descriptor& operator=(const Descriptor&) = delete;
  ~Descriptor() { Reset(); }
  int get() const { return fd_; }
  int Release() { return std::exchange(fd_, -1); }
  void Reset(int fd = -1) {
    if (fd_ >= 0) close(fd_);
    fd_ = fd;
  }

 private:
  int fd_;
};

// The request as an anonymous in-memory file (no pipe to fill, no SIGPIPE if the helper dies early).
void WriteRequest(const Points& vertices, const Faces& faces, const std::string& switches, Task task,
                  std::int64_t cpu_seconds, Descriptor* request) {
  request->Reset(memfd_create("springblend-tetgen-request", MFD_CLOEXEC));
  if (request->get() < 0) CannotStart(SystemError("memfd_create"));
  const Request header{kRequestMagic, task,          static_cast<std::int32_t>(switches.size()), vertices.rows(),
                       faces.rows(),  getpid(), cpu_seconds};
  static_assert(sizeof(int) == sizeof(std::int32_t));
  if (!WriteAll(request->get(), &header, sizeof(header)) ||
      !WriteAll(request->get(), switches.data(), switches.size()) ||
      !WriteAll(request->get(), vertices.data(), sizeof(double) * static_cast<size_t>(vertices.size())) ||
      !WriteAll(request->get(), faces.data(), sizeof(int) * static_cast<size_t>(faces.size()))) {
    CannotStart(SystemError("writing the request"));
  }
}

// A copy of `fd` numbered above the descriptors the helper gets, so that setting those up cannot clobber it.
void HighCopy(Descriptor* fd) {
  const int copy = fcntl(fd->get(), F_DUPFD_CLOEXEC, kResultFd + 1);
  if (copy < 0) CannotStart(SystemError("fcntl(F_DUPFD_CLOEXEC)"));
  fd->Reset(copy);
}

// Starts the helper reading `request` and writing to `result`; returns its pid.
pid_t Spawn(const std::string& helper, int request, int result) {
  posix_spawn_file_actions_t actions;
  posix_spawnattr_t attributes;
  if (int error = posix_spawn_file_actions_init(&actions); error != 0) {
    CannotStart(SystemError("posix_spawn_file_actions_init", error));
  }
  if (int error = posix_spawnattr_init(&attributes); error != 0) {
    posix_spawn_file_actions_destroy(&actions);
    CannotStart(SystemError("posix_spawnattr_init", error));
  }
  // Default dispositions and an empty mask for every signal (the caller may block SIGTERM for a signal thread,
  // or have set SIGPIPE to be ignored); standard streams on /dev/null (TetGen prints); nothing else inherited.
  sigset_t all, none;
  sigfillset(&all);
  sigemptyset(&none);
  int error = posix_spawnattr_setsigdefault(&attributes, &all);
  if (error == 0) error = posix_spawnattr_setsigmask(&attributes, &none);
  if (error == 0) error = posix_spawnattr_setflags(&attributes, POSIX_SPAWN_SETSIGDEF | POSIX_SPAWN_SETSIGMASK);
  if (error == 0) error = posix_spawn_file_actions_addopen(&actions, STDIN_FILENO, "/dev/null", O_RDONLY, 0);
  if (error == 0) error = posix_spawn_file_actions_addopen(&actions, STDOUT_FILENO, "/dev/null", O_WRONLY, 0);
  if (error == 0) error = posix_spawn_file_actions_adddup2(&actions, STDOUT_FILENO, STDERR_FILENO);
  if (error == 0) error = posix_spawn_file_actions_adddup2(&actions, request, kRequestFd);
  if (error == 0) error = posix_spawn_file_actions_adddup2(&actions, result, kResultFd);
  if (error == 0) error = posix_spawn_file_actions_addclosefrom_np(&actions, kResultFd + 1);

  std::string name = kHelperName;
  std::string serve = "--serve";
  char* arguments[] = {name.data(), serve.data(), nullptr};
  pid_t pid = -1;
  if (error == 0) error = posix_spawn(&pid, helper.c_str(), &actions, &attributes, arguments, environ);
  posix_spawn_file_actions_destroy(&actions);
  posix_spawnattr_destroy(&attributes);
  if (error != 0) CannotStart(SystemError(fmt::format("posix_spawn of {}", helper).c_str(), error));
  return pid;
}

}  // namespace

std::string FindHelper() {
  // A path given explicitly (SetTetGenHelper, then the variable) is the only candidate: a mistake in it is
  // reported, not hidden behind another helper found elsewhere.
  std::vector<std::string> candidates;
  {
    std::lock_guard lock(helper_mutex);
    if (!helper_override.empty()) candidates.push_back(helper_override);
  }
  if (const char* variable = std::getenv(kHelperVariable);
      candidates.empty() && variable != nullptr && *variable != '\0') {
    candidates.emplace_back(variable);
  }
  if (candidates.empty()) {
    std::error_code error;
    const std::filesystem::path program = std::filesystem::read_symlink("/proc/self/exe", error);
    if (!error) {
      candidates.push_back((program.parent_path() / kHelperName).string());
      candidates.push_back((program.parent_path() / ".." / "libexec" / "springblend" / kHelperName).string());
    }
#ifdef SPRINGBLEND_INSTALLED_TETGEN_HELPER
    candidates.emplace_back(SPRINGBLEND_INSTALLED_TETGEN_HELPER);
#endif
  }
  for (const std::string& candidate : candidates) {
    if (IsExecutableFile(candidate)) return candidate;
  }
  // An installation problem, not a property of the surface: kInternal, so that nobody falls back quietly.
  throw Error(ErrorCode::kInternal,
              fmt::format("cannot tetrahedralize the surface: no {} helper program at {} (install it there, set {} "
                          "or call SetTetGenHelper)",
                          kHelperName, fmt::join(candidates, ", "), kHelperVariable));
}

std::int64_t CpuSecondsFor(double timeout_seconds) {
  if (!(timeout_seconds < 1e6)) return 0;
  return static_cast<std::int64_t>(std::ceil(timeout_seconds)) + 1;
}

HelperProcess::HelperProcess(const Points& vertices, const Faces& faces, const std::string& switches, Task task,
                             std::int64_t cpu_seconds) {
  const std::string helper = FindHelper();
  Descriptor request;
  WriteRequest(vertices, faces, switches, task, cpu_seconds, &request);
  HighCopy(&request);
  int fds[2];
  // Close-on-exec keeps the pipe out of programs that other threads spawn meanwhile.
  if (pipe2(fds, O_CLOEXEC) != 0) CannotStart(SystemError("pipe2"));
  Descriptor read_end(fds[0]), write_end(fds[1]);
  HighCopy(&write_end);
  pid_ = Spawn(helper, request.get(), write_end.get());
  // Only the helper holds the write end now: its exit is the end of file.
  fd_ = read_end.Release();
}

HelperProcess::~HelperProcess() {
  if (pid_ > 0) Reap(true);
}

std::optional<int> HelperProcess::Reap(bool kill_first) {
  if (fd_ >= 0) close(std::exchange(fd_, -1));
  if (kill_first) kill(pid_, SIGKILL);
  int status = 0;
  pid_t reaped;
  do {
    reaped = waitpid(pid_, &status, 0);
  } while (reaped < 0 && errno == EINTR);
  pid_ = -1;
  if (reaped < 0) return std::nullopt;  // e.g. the caller set SIGCHLD to SIG_IGN
  return status;
}

Outcome HelperProcess::Collect(Clock::time_point deadline) {
  // Read while the helper writes, so that a result larger than the pipe's buffer cannot block it.
  Outcome outcome;
  std::vector<char> buffer(sizeof(MessageHeader));
  size_t received = 0;
  bool have_header = false;
  while (received < buffer.size()) {
    const auto left = std::chrono::ceil<std::chrono::milliseconds>(deadline - Clock::now()).count();
    if (left <= 0) {
      outcome.timed_out = true;
      break;
    }
    pollfd ready{fd_, POLLIN, 0};
    const int polled = poll(&ready, 1, static_cast<int>(std::min<decltype(left)>(left, 1 << 30)));
    if (polled == 0 || (polled < 0 && errno == EINTR)) continue;
    if (polled < 0) break;
    const ssize_t got = read(fd_, buffer.data() + received, buffer.size() - received);
    if (got == 0) break;  // end of file: the helper is gone
    if (got < 0) {
      if (errno == EINTR || errno == EAGAIN) continue;
      break;
    }
    received += static_cast<size_t>(got);
    if (!have_header && received == sizeof(MessageHeader)) {
      std::memcpy(&outcome.header, buffer.data(), sizeof(MessageHeader));
      const std::int64_t payload = PayloadBytes(outcome.header);
      if (payload < 0) break;
      have_header = true;
      buffer.resize(sizeof(MessageHeader) + static_cast<size_t>(payload));
    }
  }
  outcome.complete = have_header && received == buffer.size();
  // After a complete message the helper only has to _exit; otherwise it may still be running.
  outcome.wait_status = Reap(!outcome.complete);
  if (outcome.complete) outcome.payload.assign(buffer.begin() + sizeof(MessageHeader), buffer.end());
  return outcome;
}

}  // namespace internal::tetgen
}  // namespace springblend
