// What the solver and its TetGen helper (springblend-tetgen, tetgen_helper.cc) say to each other: the request
// the parent writes into an in-memory file (descriptor 3 in the helper), and the message the helper writes back
// through a pipe (descriptor 4): a header, then raw arrays in the parent's own layout (same machine, same
// build). Internal: the helper is installed with the library it belongs to.
#pragma once

#include <unistd.h>

#include <cerrno>
#include <cstddef>
#include <cstdint>
#include <limits>

namespace springblend::internal::tetgen {

constexpr int kRequestFd = 3;  // a memfd holding the request, read from offset 0
constexpr int kResultFd = 4;   // the write end of the result pipe

// What the helper is asked to do.
enum class Task : std::int32_t {
  kMesh,      // tetrahedralize with the switches; answer kMesh or a failure
  kDiagnose,  // run TetGen's -d self-intersection check; answer kIntersections or a failure
  kHold,      // for tests of the process limits: wait until killed
  kSpin,      // for tests of the process limits: burn CPU until killed
};

// The request: this header, the switches, the points (row-major doubles), the faces (row-major int32).
struct Request {
  std::uint64_t magic;
  Task task;
  std::int32_t switches_bytes;
  std::int64_t points;
  std::int64_t faces;
  std::int64_t parent;       // the pid the helper must be a child of (it dies with it)
  std::int64_t cpu_seconds;  // RLIMIT_CPU for the helper; <= 0: none
};
constexpr std::uint64_t kRequestMagic = 0x7370626c74657432ULL;  // "spbltet2"

enum class MessageKind : std::int32_t {
  kMesh,              // points = output vertices, count = tets; then points x 3 doubles, count x 4 int32
  kTetGenError,       // TetGen threw error_code
  kOutOfMemory,       // std::bad_alloc
  kUnknownException,  // anything else thrown
  kIntersections,     // the -d check: count distinct pairs of intersecting faces; then count x 2 int32
};

struct MessageHeader {
  MessageKind kind;
  std::int32_t error_code;
  std::int64_t points;
  std::int64_t count;
};

// Bytes after the header, or -1 for a header that cannot be ours.
inline std::int64_t PayloadBytes(const MessageHeader& header) {
  constexpr std::int64_t kMaxCount = std::numeric_limits<std::int32_t>::max();
  if (header.points < 0 || header.count < 0 || header.points > kMaxCount || header.count > kMaxCount) return -1;
  switch (header.kind) {
    case MessageKind::kMesh:
      return header.points * 3 * static_cast<std::int64_t>(sizeof(double)) +
             header.count * 4 * static_cast<std::int64_t>(sizeof(std::int32_t));
    case MessageKind::kIntersections:
      return header.count * 2 * static_cast<std::int64_t>(sizeof(std::int32_t));
    case MessageKind::kTetGenError:
    case MessageKind::kOutOfMemory:
    case MessageKind::kUnknownException:
      return 0;
  }
  return -1;
}

inline bool WriteAll(int fd, const void* data, size_t size) {
  const char* bytes = static_cast<const char*>(data);
  while (size > 0) {
    const ssize_t written = write(fd, bytes, size);
    if (written < 0) {
      if (errno == EINTR) continue;
      return false;
    }
    bytes += written;
    size -= static_cast<size_t>(written);
  }
  return true;
}

inline bool ReadAllAt(int fd, void* data, size_t size, off_t offset) {
  char* bytes = static_cast<char*>(data);
  while (size > 0) {
    const ssize_t got = pread(fd, bytes, size, offset);
    if (got < 0 && errno == EINTR) continue;
    if (got <= 0) return false;
    bytes += got;
    size -= static_cast<size_t>(got);
    offset += got;
  }
  return true;
}

}  // namespace springblend::internal::tetgen
