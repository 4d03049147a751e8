// libFuzzer target: the upload chunk assembler. The input is a sequence of chunks, each a little-endian
// 16-bit length and that many bytes of a serialized UploadChunk (unparseable ones are skipped, as gRPC would
// refuse them before the handler). Limits are small so a fuzzed header cannot ask for gigabytes.
#include <cstddef>
#include <cstdint>

#include "convert.h"
#include "status.h"
#include "springblend/error.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, size_t size) {
  springblend::server::Limits limits;
  limits.max_upload_bytes = 1 << 20;
  limits.max_vertices = 4096;
  limits.max_targets = 16;
  springblend::server::UploadAssembler assembler(limits);
  try {
    size_t at = 0;
    while (at + 2 <= size) {
      const size_t length = std::min<size_t>(data[at] | (size_t{data[at + 1]} << 8), size - at - 2);
      springblend::v1::UploadChunk chunk;
      if (chunk.ParseFromArray(data + at + 2, static_cast<int>(length))) assembler.Add(chunk);
      at += 2 + length;
    }
    assembler.Finish();
  } catch (const springblend::Error&) {
  } catch (const springblend::server::LimitError&) {  // over a limit: RESOURCE_EXHAUSTED, a refusal too
  }
  return 0;
}
