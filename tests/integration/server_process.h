// Helpers of the integration tests that drive a real springblend-server process: starting and stopping it,
// a small rig, request builders and status probes.
#pragma once

#include <arpa/inet.h>
#include <fcntl.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cstdio>
#include <fstream>
#include <functional>
#include <string>
#include <vector>

#include "springblend/client.h"
#include "test_util.h"

namespace springblend::testing {

// A server process; stopped with SIGTERM (the graceful path) when the object goes. Its log (stderr) goes to
// log_file when one is given; `in_child` runs in the child before the server is started (limits to set with
// setrlimit, signals to ignore: both last across exec).
class ServerProcess {
 public:
  ServerProcess(const std::string& cache_dir, std::vector<std::string> extra = {}, const std::string& log_file = "",
                const std::function<void()>& in_child = {}) {
    int out[2];
    EXPECT_EQ(pipe(out), 0);
    pid_ = fork();
    if (pid_ == 0) {
      if (in_child) in_child();
      dup2(out[1], STDOUT_FILENO);
      close(out[0]);
      if (!log_file.empty()) {
        const int log = open(log_file.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
        if (log >= 0) dup2(log, STDERR_FILENO);
      }
      std::vector<std::string> args = {SPRINGBLEND_SERVER, "--listen", "127.0.0.1:0", "--cache-dir", cache_dir};
      args.insert(args.end(), extra.begin(), extra.end());
      std::vector<char*> argv;
      for (auto& a : args) argv.push_back(a.data());
      argv.push_back(nullptr);
      execv(argv[0], argv.data());
      _exit(127);
    }
    close(out[1]);
    // Lines until "springblend-server listening on 127.0.0.1:PORT" (after "... metrics on http://..." and
    // "... health on 127.0.0.1:PORT").
    for (int lines = 0; lines < 4 && address_.empty(); ++lines) {
      std::string line;
      char c;
      while (read(out[0], &c, 1) == 1 && c != '\n') line += c;
      const auto colon = line.rfind(':');
      if (colon == std::string::npos) break;
      if (line.find("metrics on") != std::string::npos) {
        metrics_port_ = std::stoi(line.substr(colon + 1));
      } else if (line.find("health on") != std::string::npos) {
        health_address_ = "127.0.0.1:" + line.substr(colon + 1);
      } else if (line.find("listening on") != std::string::npos) {
        address_ = "127.0.0.1:" + line.substr(colon + 1);
      }
    }
    close(out[0]);
  }
  int metrics_port() const { return metrics_port_; }
  // The plaintext health-only address (--health-address), empty without one.
  const std::string& health_address() const { return health_address_; }
  ~ServerProcess() { Stop(); }
  // kill -9: no draining, no clean-up; what a crash or an OOM kill leaves.
  void Kill() {
    if (pid_ <= 0) return;
    kill(pid_, SIGKILL);
    waitpid(pid_, nullptr, 0);
    pid_ = -1;
  }
  pid_t pid() const { return pid_; }
  // SIGTERM, then the exit code. A server that started must exit 0: anything else (a crash, or a sanitizer
  // report, which sanitized builds turn into an exit code) fails the test.
  int Stop() {
    if (pid_ <= 0) return -1;
    kill(pid_, SIGTERM);
    int status = 0;
    waitpid(pid_, &status, 0);
    pid_ = -1;
    const int code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
    if (!address_.empty()) {
      EXPECT_EQ(code, 0) << "the server at " << address_ << " did not exit cleanly"
                         << (WIFSIGNALED(status) ? " (signal " + std::to_string(WTERMSIG(status)) + ")" : "");
    }
    return code;
  }
  const std::string& address() const { return address_; }

 private:
  pid_t pid_ = -1;
  std::string address_;
  std::string health_address_;
  int metrics_port_ = 0;
};

struct ServerRun {
  int exit_code = -1;
  std::string output;  // stdout and stderr
};

// Runs springblend-server with these arguments; one that starts is stopped by `timeout` (exit code 124).
inline ServerRun RunServer(const TempDir& dir, const std::vector<std::string>& arguments) {
  std::string command = "timeout 10 " + std::string(SPRINGBLEND_SERVER) + " --cache-dir " + dir.File("cache");
  for (const auto& a : arguments) command += " '" + a + "'";
  command += " 2>&1 </dev/null";
  ServerRun run;
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) return run;
  std::array<char, 4096> buffer;
  size_t n;
  while ((n = fread(buffer.data(), 1, buffer.size(), pipe)) > 0) run.output.append(buffer.data(), n);
  const int status = pclose(pipe);
  run.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return run;
}

struct CylinderRig {
  TriangleMesh rest = LoadMesh(DataPath("cylinder/cylinder.obj"));
  std::vector<TriangleMesh> targets = {LoadMesh(DataPath("cylinder/poses-2_cylinder-1.obj")),
                                       LoadMesh(DataPath("cylinder/poses-2_cylinder-3.obj"))};
};

v1::SolveRequest SweepRequest(const std::string& id, int frames, const std::vector<double>& end) {
  v1::SolveRequest request;
  request.set_character_id(id);
  for (const auto& frame : SweepFrames(end, frames)) {
    v1::FrameRequest* f = request.add_frames();
    for (double w : frame.weights) f->add_weights(w);
  }
  return request;
}

int StatusOf(const std::function<void()>& call) {
  try {
    call();
  } catch (const ClientError& e) {
    return e.code();
  }
  return 0;
}

std::string MessageOf(const std::function<void()>& call) {
  try {
    call();
  } catch (const ClientError& e) {
    return e.what();
  }
  return "";
}

// GET a path from 127.0.0.1:port; returns the whole response.
inline std::string HttpGet(int port, const std::string& path) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<std::uint16_t>(port));
  inet_pton(AF_INET, "127.0.0.1", &address.sin_addr);
  std::string response;
  if (connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) == 0) {
    const std::string request = "GET " + path + " HTTP/1.0\r\n\r\n";
    send(fd, request.data(), request.size(), 0);
    char buffer[4096];
    ssize_t n;
    while ((n = recv(fd, buffer, sizeof(buffer), 0)) > 0) response.append(buffer, static_cast<size_t>(n));
  }
  close(fd);
  return response;
}

// A metric's value from the server's /metrics on 127.0.0.1:port; -1 when it is not there.
inline double Metric(int port, const std::string& name) {
  const std::string text = HttpGet(port, "/metrics");
  const auto at = text.find("\n" + name + " ");
  return at == std::string::npos ? -1.0 : std::stod(text.substr(at + name.size() + 2));
}

// Resident memory of a process, in MiB (0 when it is gone).
inline double RssMb(pid_t pid) {
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  std::string key;
  while (status >> key) {
    if (key == "VmRSS:") {
      double kb = 0;
      status >> kb;
      return kb / 1024.0;
    }
    status.ignore(1 << 12, '\n');
  }
  return 0.0;
}

}  // namespace springblend::testing
