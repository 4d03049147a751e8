// libFuzzer target: the CLI's take reader (ParseTake, which ReadTake calls on a file's text) and the matching of
// what it read to a rig's targets (MatchTake, both ways of treating lost rows), as `--take FILE` runs them.
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "springblend/error.h"
#include "take.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, size_t size) {
  static const std::vector<std::string> kTargets = {"jawOpen", "browInnerUp_L", "browInnerUp_R", "eyeBlinkL",
                                                    "EyeBlink.R", "mouthLeft", "cheekPuff"};
  try {
    const springblend::cli::Take take =
        springblend::cli::ParseTake(std::string(reinterpret_cast<const char*>(data), size), "fuzz.csv");
    for (const auto lost : {springblend::cli::LostRows::kHold, springblend::cli::LostRows::kSkip}) {
      const springblend::cli::TakeFrames frames = springblend::cli::MatchTake(take, kTargets, nullptr, lost);
      (void)frames.report.Lines();
    }
  } catch (const springblend::Error&) {
  }
  return 0;
}
