// libFuzzer target: the mesh loaders (OpenMesh readers behind LoadMeshFromText, then ValidateMesh). The first
// byte picks the format; the rest is the file. Any springblend::Error is a correct refusal; anything else
// (a crash, a sanitizer report, another exception) is a finding.
#include <cstddef>
#include <cstdint>
#include <string>

#include "springblend/error.h"
#include "springblend/mesh.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, size_t size) {
  if (size < 1) return 0;
  static const char* const kFormats[] = {"obj", "off", "ply", "stl"};
  const std::string format = kFormats[data[0] % 4];
  const std::string text(reinterpret_cast<const char*>(data + 1), size - 1);
  try {
    springblend::LoadMeshFromText(text, format, "fuzz." + format);
  } catch (const springblend::Error&) {
  }
  return 0;
}
