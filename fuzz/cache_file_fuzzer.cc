// libFuzzer target: the cache file payload parser (Deserialize), which reads what another replica, an older
// version or a damaged disk left in the cache directory. (The file's checksum is checked before it; this is
// the parser that must hold even if a file passes that check by accident.)
#include <cstddef>
#include <cstdint>
#include <string>

#include "character_store.h"
#include "springblend/error.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, size_t size) {
  try {
    const springblend::server::CharacterData d =
        springblend::server::Deserialize(std::string(reinterpret_cast<const char*>(data), size));
    springblend::server::ContentId(d);
  } catch (const springblend::Error&) {
  }
  return 0;
}
