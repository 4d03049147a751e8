// Helpers of the integration tests that drive a real springblend-server process: starting and stopping it,
// a small rig, request builders and status probes.
#pragma once

#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <functional>
#include <string>
#include <vector>

#include "springblend/client.h"
#include "test_util.h"

namespace springblend::testing {

// A server process; stopped with SIGTERM (the graceful path) when the object goes.
class ServerProcess {
 public:
  ServerProcess(const std::string& cache_dir, std::vector<std::string> extra = {}) {
    int out[2];
    EXPECT_EQ(pipe(out), 0);
    pid_ = fork();
    if (pid_ == 0) {
      dup2(out[1], STDOUT_FILENO);
      close(out[0]);
      std::vector<std::string> args = {SPRINGBLEND_SERVER, "--listen", "127.0.0.1:0", "--cache-dir", cache_dir};
      args.insert(args.end(), extra.begin(), extra.end());
      std::vector<char*> argv;
      for (auto& a : args) argv.push_back(a.data());
      argv.push_back(nullptr);
      execv(argv[0], argv.data());
      _exit(127);
    }
    close(out[1]);
    // Lines until "springblend-server listening on 127.0.0.1:PORT" (after "... metrics on http://...").
    for (int lines = 0; lines < 4 && address_.empty(); ++lines) {
      std::string line;
      char c;
      while (read(out[0], &c, 1) == 1 && c != '\n') line += c;
      const auto colon = line.rfind(':');
      if (colon == std::string::npos) break;
      if (line.find("metrics on") != std::string::npos) {
        metrics_port_ = std::stoi(line.substr(colon + 1));
      } else if (line.find("listening on") != std::string::npos) {
        address_ = "127.0.0.1:" + line.substr(colon + 1);
      }
    }
    close(out[0]);
  }
  int metrics_port() const { return metrics_port_; }
  ~ServerProcess() { Stop(); }
  // kill -9: no draining, no clean-up; what a crash or an OOM kill leaves.
  void Kill() {
    if (pid_ <= 0) return;
    kill(pid_, SIGKILL);
    waitpid(pid_, nullptr, 0);
    pid_ = -1;
  }
  pid_t pid() const { return pid_; }
  int Stop() {
    if (pid_ <= 0) return -1;
    kill(pid_, SIGTERM);
    int status = 0;
    waitpid(pid_, &status, 0);
    pid_ = -1;
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  }
  const std::string& address() const { return address_; }

 private:
  pid_t pid_ = -1;
  std::string address_;
  int metrics_port_ = 0;
};

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

}  // namespace springblend::testing
