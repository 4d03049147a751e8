// Runs the springblend CLI as users and scripts do: a real process, its stdout as JSON lines, its stderr and
// its exit code. SPRINGBLEND_CLI is the binary (tests/CMakeLists.txt).
#pragma once

#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <vector>

#include "test_util.h"

namespace springblend::testing {

struct CliRun {
  int exit_code = -1;
  std::vector<nlohmann::json> lines;  // stdout, one JSON document per line
  std::string stderr_text;
};

// `arguments` follow the binary; `environment` ("NAME=value ...") goes before it, for the shell.
inline CliRun RunCli(const std::string& arguments, const TempDir& dir, const std::string& environment = "") {
  const std::string err = dir.File("stderr.txt");
  const std::string command = environment + " " + std::string(SPRINGBLEND_CLI) + " " + arguments + " 2>" + err;
  CliRun run;
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) return run;
  std::string out;
  std::array<char, 4096> buffer;
  size_t n;
  while ((n = fread(buffer.data(), 1, buffer.size(), pipe)) > 0) out.append(buffer.data(), n);
  const int status = pclose(pipe);
  run.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  std::istringstream lines(out);
  for (std::string line; std::getline(lines, line);) {
    if (!line.empty()) run.lines.push_back(nlohmann::json::parse(line));
  }
  std::ifstream in(err);
  run.stderr_text.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  return run;
}

}  // namespace springblend::testing
