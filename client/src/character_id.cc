// A character's id computed on the client, before its upload (docs/server.md#routing): the hex SHA-256 of the
// canonical bytes the server hashes (server/character_store.cc, SerializeWithName with an empty name). The
// bytes are little-endian and follow the upload's header and arrays field by field, with the defaults the
// server fills in for zero options. integration_server_test checks, rig by rig, that the server gives the
// same id; a server that does not logs and counts it (springblend_upload_routing_mismatches_total).
#include <openssl/evp.h>

#include <cstdint>
#include <cstring>
#include <string>

#include "springblend/client.h"

namespace springblend {
namespace {

// After the shapes of a production rig; plain characters end before it. Then, when target paths are off,
// the options' marker and a zero byte.
constexpr char kRigMarker[8] = {'S', 'B', 'R', 'I', 'G', '0', '0', '1'};
constexpr char kOptionsMarker[8] = {'S', 'B', 'O', 'P', 'T', '0', '0', '1'};
// RigOptions' defaults, which a zero BuildOptions field means.
constexpr double kDefaultStaticTolerance = 1e-6;
constexpr std::uint32_t kDefaultPathIntervals = 16;   // RigOptions::path_intervals
constexpr std::uint32_t kDefaultPathMaxSamples = 64;  // RigOptions::path_max_samples
constexpr double kDefaultBendingStiffness = 1.0;

class CanonicalBytes {
 public:
  template <typename T>
  void Put(T value) {
    bytes_.append(reinterpret_cast<const char*>(&value), sizeof(T));
  }
  void PutString(const std::string& s) {
    Put<std::uint32_t>(static_cast<std::uint32_t>(s.size()));
    bytes_.append(s);
  }
  void PutBytes(const void* data, size_t n) {
    if (n > 0) bytes_.append(static_cast<const char*>(data), n);
  }
  std::string HexSha256() const {
    unsigned char digest[EVP_MAX_MD_SIZE];
    unsigned int length = 0;
    EVP_Digest(bytes_.data(), bytes_.size(), digest, &length, EVP_sha256(), nullptr);
    static constexpr char kHex[] = "0123456789abcdef";
    std::string hex;
    for (unsigned int i = 0; i < length; ++i) {
      hex += kHex[digest[i] >> 4];
      hex += kHex[digest[i] & 15];
    }
    return hex;
  }

 private:
  std::string bytes_;
};

}  // namespace

std::string CharacterId(const TriangleMesh& rest, const std::vector<RigTarget>& targets,
                        const v1::BuildOptions& options) {
  CanonicalBytes w;
  w.PutString("");  // the name is a label, not part of the id
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(options.fixed_vertices_size()));
  for (std::uint32_t v : options.fixed_vertices()) w.Put<std::int32_t>(static_cast<std::int32_t>(v));
  w.Put<double>(options.static_tolerance() != 0.0 ? options.static_tolerance() : kDefaultStaticTolerance);
  w.Put<std::uint8_t>(options.no_interior() ? 0 : 1);
  w.Put<std::uint8_t>(options.no_anchor() ? 0 : 1);
  w.Put<double>(options.bending_stiffness() != 0.0 ? options.bending_stiffness() : kDefaultBendingStiffness);
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(targets.size()));
  for (const RigTarget& t : targets) w.PutString(t.mesh.name);
  // Row-major Eigen storage is the wire's packed triples.
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(rest.faces.rows()));
  w.PutBytes(rest.faces.data(), sizeof(int) * static_cast<size_t>(rest.faces.size()));
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(rest.vertices.rows()));
  w.PutBytes(rest.vertices.data(), sizeof(double) * static_cast<size_t>(rest.vertices.size()));
  for (const RigTarget& t : targets) {
    w.PutBytes(t.mesh.vertices.data(), sizeof(double) * static_cast<size_t>(t.mesh.vertices.size()));
  }
  bool production = false;
  for (const RigTarget& t : targets) {
    production = production || !t.inbetweens.empty() || !t.mask.empty() || !t.combination.empty();
  }
  if (production) {
    w.PutBytes(kRigMarker, sizeof(kRigMarker));
    for (const RigTarget& t : targets) {
      w.Put<std::uint32_t>(static_cast<std::uint32_t>(t.inbetweens.size()));
      for (const RigTarget::Inbetween& b : t.inbetweens) {
        w.Put<double>(b.weight);
        w.PutBytes(b.mesh.vertices.data(), sizeof(double) * static_cast<size_t>(b.mesh.vertices.size()));
      }
      w.Put<std::uint8_t>(t.mask.empty() ? 0 : 1);
      w.PutBytes(t.mask.data(), sizeof(double) * t.mask.size());
      w.Put<std::uint32_t>(static_cast<std::uint32_t>(t.combination.size()));
      for (const std::string& driver : t.combination) w.PutString(driver);
    }
  }
  // The server's options tail (character_store.cc): only where an option differs from the default.
  const std::uint32_t intervals = options.path_intervals() != 0 ? options.path_intervals() : kDefaultPathIntervals;
  const std::uint32_t samples = options.path_max_samples() != 0 ? options.path_max_samples() : kDefaultPathMaxSamples;
  const bool density = intervals != kDefaultPathIntervals || samples != kDefaultPathMaxSamples;
  if (options.no_target_paths() || options.hold_outer_rim() || density) {
    w.PutBytes(kOptionsMarker, sizeof(kOptionsMarker));
    w.Put<std::uint8_t>(options.no_target_paths() ? 0 : 1);
    if (options.hold_outer_rim() || density) w.Put<std::uint8_t>(options.hold_outer_rim() ? 1 : 0);
    if (density) {
      w.Put<std::uint32_t>(intervals);
      w.Put<std::uint32_t>(samples);
    }
  }
  return w.HexSha256();
}

}  // namespace springblend
