// libFuzzer target: the mesh loaders (OpenMesh's OBJ and STL readers behind our checks, our OFF reader; PLY on
// request, below) behind LoadMeshFromText, then ValidateMesh. The first byte picks the format (0 OBJ, 1 OFF, 2 STL,
// modulo 3; with PLY, 3 PLY, modulo 4); the rest is the file. Any springblend::Error is a correct refusal; anything
// else (a crash, a sanitizer report, another exception, a hang or an allocation past -rss_limit_mb) is a finding.
//
// PLY (a CLI format; the server parses only OBJ) is left out unless SPRINGBLEND_FUZZ_PLY=1: OpenMesh 9.0's PLY
// reader trusts a face's corner count in the body, ASCII or binary ("4000000000 0 1 2" allocates until the
// process dies), which no header check can see. (Its header findings, a version that is not a number and words it
// reads as keywords, are refused or neutralised by CheckPly.) Fixing that means a PLY reader of our own, as OFF has.
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "springblend/error.h"
#include "springblend/mesh.h"

namespace {

const char* const kFormats[] = {"obj", "off", "stl", "ply"};
unsigned long long executions[4] = {};

// At exit (libFuzzer exits when its time is up), how many inputs each format got; fuzz/run.sh reports it.
void PrintExecutionsByFormat() {
  std::fprintf(stderr, "mesh_loader_fuzzer executions by format: obj %llu, off %llu, stl %llu, ply %llu\n",
               executions[0], executions[1], executions[2], executions[3]);
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  std::atexit(PrintExecutionsByFormat);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, size_t size) {
  static const unsigned formats = std::getenv("SPRINGBLEND_FUZZ_PLY") != nullptr ? 4 : 3;
  if (size < 1) return 0;
  const unsigned index = data[0] % formats;
  ++executions[index];
  const std::string format = kFormats[index];
  const std::string text(reinterpret_cast<const char*>(data + 1), size - 1);
  try {
    springblend::LoadMeshFromText(text, format, "fuzz." + format);
  } catch (const springblend::Error&) {
  }
  return 0;
}
