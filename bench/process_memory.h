// The benchmarks' reading of their own memory from /proc/self (Linux).
#pragma once

#include <fstream>
#include <optional>
#include <sstream>
#include <string>

namespace springblend::bench {

// A line of /proc/self/status in MB (VmRSS: the resident set now; VmHWM: its high-water mark); nullopt where
// there is none.
inline std::optional<double> StatusMb(const std::string& key) {
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind(key + ":", 0) == 0) {
      std::istringstream fields(line.substr(key.size() + 1));
      double kb = 0.0;
      if (fields >> kb) return kb / 1024.0;
    }
  }
  return std::nullopt;
}

// Resets the resident set's high-water mark (VmHWM) to the resident set now, so a measurement's peak is its own.
// False where the kernel does not allow it.
inline bool ResetPeakRss() { return static_cast<bool>(std::ofstream("/proc/self/clear_refs") << "5" << std::flush); }

}  // namespace springblend::bench
