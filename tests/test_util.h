// Helpers shared by the tests: paths to the bundled meshes, small rigs, geometric measures.
#pragma once

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "springblend/error.h"
#include "springblend/mesh.h"
#include "springblend/rig.h"
#include "springblend/solve.h"

namespace springblend::testing {

// How much slower the instrumented builds run (AddressSanitizer, ThreadSanitizer): liveness bounds in tests
// (a build stops within a second of its stop check) scale by it, so they bound the work, not the instruments.
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
constexpr double kSlowdown = 10.0;
#else
constexpr double kSlowdown = 1.0;
#endif

inline std::string DataPath(const std::string& relative) {
  return std::string(SPRINGBLEND_TEST_DATA) + "/" + relative;
}

// Rig options for tests of everything but the target paths themselves: paths swept at 8 steps per unit rather
// than the default 16 (a frame's answer still starts from its own target's path; solver_target_paths_test and
// the server's restart tests build the default paths), so the suites stay within CI's time under the sanitizers.
inline RigOptions TestRigOptions() {
  RigOptions options;
  options.path_intervals = 8;
  return options;
}

// Rig options for tests whose answers do not depend on where a frame's solve starts (the rig's structure and
// summary, boundary conditions, weight semantics, masks, pins, the linear-algebra backends): no target paths,
// so frames start from the linear blend and a rig builds in a tenth of the time (the two-target cylinder: 0.6
// against 6.8 s under ASan, 0.13 against 1.0 s in release).
inline RigOptions NoPathsRigOptions() {
  RigOptions options = TestRigOptions();
  options.target_paths = false;
  return options;
}

inline std::shared_ptr<const Rig> LoadRig(const std::string& rest, const std::vector<std::string>& targets,
                                          const RigOptions& options = TestRigOptions()) {
  std::vector<TriangleMesh> meshes;
  for (const auto& t : targets) meshes.push_back(LoadMesh(DataPath(t)));
  return Rig::Build(LoadMesh(DataPath(rest)), std::move(meshes), options);
}

// Largest vertex distance between two equally sized point sets.
inline double MaxDistance(const Points& a, const Points& b) {
  return (a - b).rowwise().norm().maxCoeff();
}

// A temporary directory removed at scope exit.
class TempDir {
 public:
  TempDir() {
    path_ = std::filesystem::temp_directory_path() /
            ("springblend-test-" + std::to_string(::getpid()) + "-" + std::to_string(counter_++));
    std::filesystem::create_directories(path_);
  }
  ~TempDir() {
    std::error_code ec;
    std::filesystem::remove_all(path_, ec);
  }
  std::string File(const std::string& name) const { return (path_ / name).string(); }
  std::string Write(const std::string& name, const std::string& text) const {
    std::ofstream(File(name)) << text;
    return File(name);
  }
  const std::filesystem::path& path() const { return path_; }

 private:
  static inline int counter_ = 0;
  std::filesystem::path path_;
};

// Runs fn and returns the springblend::Error it throws (fails the test if it throws nothing).
template <typename Fn>
Error CatchError(Fn&& fn) {
  try {
    fn();
  } catch (const Error& e) {
    return e;
  }
  ADD_FAILURE() << "expected springblend::Error";
  return Error(ErrorCode::kInternal, "no error thrown");
}

}  // namespace springblend::testing
