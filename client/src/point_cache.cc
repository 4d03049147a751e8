#include "springblend/point_cache.h"

#include <fcntl.h>
#include <fmt/format.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <filesystem>

namespace springblend {
namespace {

constexpr char kSignature[12] = {'P', 'O', 'I', 'N', 'T', 'C', 'A', 'C', 'H', 'E', '2', '\0'};
constexpr std::int32_t kVersion = 1;
constexpr std::streamoff kSampleCountOffset = 28;  // signature, version, points, start, rate
constexpr std::size_t kHeaderBytes = 32;

// 4-byte values in little-endian order, whatever the host's.
template <typename T>
std::array<char, 4> Little(T value) {
  static_assert(sizeof(T) == 4);
  std::uint32_t bits;
  std::memcpy(&bits, &value, 4);
  return {static_cast<char>(bits), static_cast<char>(bits >> 8), static_cast<char>(bits >> 16),
          static_cast<char>(bits >> 24)};
}

template <typename T>
T FromLittle(const char* bytes) {
  static_assert(sizeof(T) == 4);
  const auto* b = reinterpret_cast<const unsigned char*>(bytes);
  const std::uint32_t bits = std::uint32_t{b[0]} | std::uint32_t{b[1]} << 8 | std::uint32_t{b[2]} << 16 |
                             std::uint32_t{b[3]} << 24;
  T value;
  std::memcpy(&value, &bits, 4);
  return value;
}

}  // namespace

PointCacheWriter::PointCacheWriter(std::string path, int num_points, float start_frame, float sample_rate)
    : path_(std::move(path)), partial_path_(path_ + ".partial"), num_points_(num_points) {
  if (num_points <= 0) throw PointCacheError(fmt::format("{}: a point cache needs points, got {}", path_, num_points));
  // The temporary is created afresh and never through a link: a planted NAME.pc2.partial -> victim must not
  // get the victim overwritten. A stale regular partial (an earlier run killed mid-write) is removed first;
  // anything else there (a link, a directory, a FIFO) is refused.
  struct stat existing {};
  if (lstat(partial_path_.c_str(), &existing) == 0 && S_ISREG(existing.st_mode)) ::unlink(partial_path_.c_str());
  fd_ = ::open(partial_path_.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC, 0644);
  if (fd_ < 0) {
    const int error = errno;
    throw PointCacheError(fmt::format("{}: cannot write the point cache: {} ({}){}", path_, partial_path_,
                                      std::strerror(error),
                                      error == EEXIST || error == ELOOP
                                          ? "; it is not a regular file (a link?): remove it"
                                          : ""));
  }
  WriteBytes(kSignature, sizeof kSignature);
  for (const auto& field : {Little(kVersion), Little(std::int32_t{num_points}), Little(start_frame),
                            Little(sample_rate), Little(std::int32_t{0})}) {
    WriteBytes(field.data(), field.size());
  }
}

PointCacheWriter::~PointCacheWriter() {
  if (closed_) return;
  if (fd_ >= 0) ::close(fd_);
  ::unlink(partial_path_.c_str());  // ours: created with O_EXCL (unlink removes a link, never its target)
}

void PointCacheWriter::WriteBytes(const char* data, std::size_t size) {
  while (size > 0) {
    const ssize_t n = ::write(fd_, data, size);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) throw PointCacheError(fmt::format("{}: writing the point cache failed ({})", path_, std::strerror(errno)));
    data += n;
    size -= static_cast<std::size_t>(n);
  }
}

// Samples are float32: one that is not finite as float32 (a coordinate beyond 3.4e38) is refused, not written.
void PointCacheWriter::CheckFinite(const float* values, std::size_t count) const {
  for (std::size_t i = 0; i < count; ++i) {
    if (!std::isfinite(values[i])) {
      throw PointCacheError(fmt::format("{}: sample {} has a non-finite coordinate (point {}, {}): not written",
                                        path_, samples_, i / 3, values[i]));
    }
  }
}

void PointCacheWriter::Add(const Points& positions) {
  if (closed_) throw PointCacheError(fmt::format("{}: the point cache is closed", path_));
  if (positions.rows() != num_points_) {
    throw PointCacheError(fmt::format("{}: sample {} has {} points, the cache {}", path_, samples_,
                                      positions.rows(), num_points_));
  }
  std::vector<char> bytes(static_cast<std::size_t>(num_points_) * 12);
  std::vector<float> values(static_cast<std::size_t>(num_points_) * 3);
  for (Eigen::Index i = 0; i < positions.rows(); ++i) {
    for (int c = 0; c < 3; ++c) values[static_cast<std::size_t>(i * 3 + c)] = static_cast<float>(positions(i, c));
  }
  CheckFinite(values.data(), values.size());
  for (std::size_t k = 0; k < values.size(); ++k) std::memcpy(bytes.data() + k * 4, Little(values[k]).data(), 4);
  WriteBytes(bytes.data(), bytes.size());
  ++samples_;
}

void PointCacheWriter::AddPacked(const std::string& float32_xyz) {
  if (closed_) throw PointCacheError(fmt::format("{}: the point cache is closed", path_));
  if (float32_xyz.size() != static_cast<std::size_t>(num_points_) * 12) {
    throw PointCacheError(fmt::format("{}: sample {} has {} bytes, the cache needs {} ({} points)", path_, samples_,
                                      float32_xyz.size(), num_points_ * 12, num_points_));
  }
  std::vector<float> values(float32_xyz.size() / 4);
  for (std::size_t k = 0; k < values.size(); ++k) values[k] = FromLittle<float>(float32_xyz.data() + k * 4);
  CheckFinite(values.data(), values.size());
  WriteBytes(float32_xyz.data(), float32_xyz.size());  // already float32 little-endian x y z
  ++samples_;
}

void PointCacheWriter::Close() {
  if (closed_) return;
  const auto count = Little(std::int32_t{samples_});
  if (::lseek(fd_, kSampleCountOffset, SEEK_SET) != kSampleCountOffset) {
    throw PointCacheError(fmt::format("{}: writing the point cache failed ({})", path_, std::strerror(errno)));
  }
  WriteBytes(count.data(), count.size());
  const int fd = fd_;
  fd_ = -1;
  if (::close(fd) != 0) {
    throw PointCacheError(fmt::format("{}: writing the point cache failed ({})", path_, std::strerror(errno)));
  }
  std::error_code error;
  std::filesystem::rename(partial_path_, path_, error);
  if (error) throw PointCacheError(fmt::format("{}: cannot put the point cache in place ({})", path_, error.message()));
  closed_ = true;
}

PointCache ReadPointCache(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw PointCacheError(fmt::format("{}: cannot read the point cache ({})", path, std::strerror(errno)));
  std::array<char, kHeaderBytes> header{};
  if (!in.read(header.data(), header.size()) || std::memcmp(header.data(), kSignature, sizeof kSignature) != 0) {
    throw PointCacheError(fmt::format("{}: not a PC2 point cache (no POINTCACHE2 signature)", path));
  }
  const auto version = FromLittle<std::int32_t>(header.data() + 12);
  const auto points = FromLittle<std::int32_t>(header.data() + 16);
  PointCache cache;
  cache.start_frame = FromLittle<float>(header.data() + 20);
  cache.sample_rate = FromLittle<float>(header.data() + 24);
  const auto samples = FromLittle<std::int32_t>(header.data() + 28);
  if (version != kVersion || points <= 0 || samples < 0) {
    throw PointCacheError(
        fmt::format("{}: unsupported PC2 header (version {}, {} points, {} samples)", path, version, points, samples));
  }
  const std::uintmax_t expected = kHeaderBytes + std::uintmax_t{12} * points * samples;
  if (std::filesystem::file_size(path) != expected) {
    throw PointCacheError(fmt::format("{}: {} bytes, but {} samples of {} points take {}", path,
                                      std::filesystem::file_size(path), samples, points, expected));
  }
  std::vector<char> bytes(static_cast<std::size_t>(points) * 12);
  for (int s = 0; s < samples; ++s) {
    if (!in.read(bytes.data(), static_cast<std::streamsize>(bytes.size()))) {
      throw PointCacheError(fmt::format("{}: sample {} is cut short", path, s));
    }
    Points& sample = cache.samples.emplace_back(points, 3);
    for (int i = 0; i < points; ++i) {
      for (int c = 0; c < 3; ++c) sample(i, c) = FromLittle<float>(bytes.data() + (i * 3 + c) * 4);
    }
  }
  return cache;
}

bool IsPointCachePath(const std::string& path) {
  if (path.size() < 4) return false;
  std::string extension = path.substr(path.size() - 4);
  std::transform(extension.begin(), extension.end(), extension.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return extension == ".pc2";
}

}  // namespace springblend
