// libFuzzer target: the CLI's JSON frames file parser (ParseScene), which LoadScene calls on a file's text.
#include <cstddef>
#include <cstdint>
#include <string>

#include "scene.h"
#include "springblend/error.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, size_t size) {
  try {
    springblend::cli::ParseScene(std::string(reinterpret_cast<const char*>(data), size), "fuzz.json");
  } catch (const springblend::Error&) {
  }
  return 0;
}
