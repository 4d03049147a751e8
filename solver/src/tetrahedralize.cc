// TetGen 1.5 ends a failed run by throwing an int (or, built without TETLIBRARY, by exit()), can crash or loop
// forever on bad input, and prints to stdout. So it never runs in the caller's process: a child process (this
// same executable, spawned and exec'd, see "The child" below) runs it and sends the result back through a pipe
// as raw arrays; the parent reads it under a deadline, reaps the child and turns every way the child can end
// into an Error.
#include "tetrahedralize.h"

#include <Eigen/Geometry>
#include <fcntl.h>
#include <fmt/format.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <tetgen.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <new>
#include <numeric>
#include <optional>
#include <string>
#include <system_error>
#include <tuple>
#include <utility>
#include <vector>

#include "springblend/error.h"

namespace springblend::internal {
namespace {

using Clock = std::chrono::steady_clock;
using Triangle = std::array<int, 3>;

// Why a surface cannot be tetrahedralized; `what` completes "cannot tetrahedralize the surface: ".
struct Failure {
  ErrorCode code;
  std::string what;
};

Error ToError(const Failure& failure) {
  return Error(failure.code, "cannot tetrahedralize the surface: " + failure.what);
}

[[noreturn]] void Refuse(const std::string& what) { throw ToError({ErrorCode::kInvalidInput, what}); }

Failure TetGenFailed(const std::string& what) { return {ErrorCode::kNumerical, "TetGen " + what}; }

// ---------------------------------------------------------------------------------------------------------
// Checks in the caller's process, before TetGen sees the surface.

void CheckOptions(const TetrahedralizeOptions& options) {
  const auto refuse = [](const std::string& what) {
    throw Error(ErrorCode::kInvalidInput, "TetrahedralizeOptions: " + what);
  };
  if (!(options.radius_edge_ratio > 1.0) || !std::isfinite(options.radius_edge_ratio)) {
    refuse(fmt::format("radius_edge_ratio must be a finite number > 1 (got {})", options.radius_edge_ratio));
  }
  if (!std::isfinite(options.max_volume)) refuse(fmt::format("max_volume must be finite (got {})", options.max_volume));
  if (!(options.timeout_seconds > 0.0) || !std::isfinite(options.timeout_seconds)) {
    refuse(fmt::format("timeout_seconds must be a finite number > 0 (got {})", options.timeout_seconds));
  }
}

// One side of a face: the edge (lo, hi) with lo < hi, and whether the face runs along it from lo to hi.
struct HalfEdge {
  int lo, hi, face;
  bool forward;
};

// Every edge must join exactly two faces that run along it in opposite directions.
void CheckClosedManifoldOriented(const Faces& faces) {
  std::vector<HalfEdge> half_edges;
  half_edges.reserve(3 * static_cast<size_t>(faces.rows()));
  for (int f = 0; f < faces.rows(); ++f) {
    for (int k = 0; k < 3; ++k) {
      const int a = faces(f, k), b = faces(f, (k + 1) % 3);
      half_edges.push_back({std::min(a, b), std::max(a, b), f, a < b});
    }
  }
  std::sort(half_edges.begin(), half_edges.end(),
            [](const HalfEdge& x, const HalfEdge& y) { return std::tie(x.lo, x.hi) < std::tie(y.lo, y.hi); });

  std::optional<HalfEdge> boundary, non_manifold, misoriented;
  int boundary_count = 0, non_manifold_count = 0, misoriented_count = 0, non_manifold_faces = 0;
  for (size_t begin = 0, end = 0; begin < half_edges.size(); begin = end) {
    while (end < half_edges.size() && half_edges[end].lo == half_edges[begin].lo &&
           half_edges[end].hi == half_edges[begin].hi) {
      ++end;
    }
    const HalfEdge& e = half_edges[begin];
    if (end - begin == 1) {
      if (boundary_count++ == 0) boundary = e;
    } else if (end - begin > 2) {
      if (non_manifold_count++ == 0) {
        non_manifold = e;
        non_manifold_faces = static_cast<int>(end - begin);
      }
    } else if (e.forward == half_edges[begin + 1].forward) {
      if (misoriented_count++ == 0) misoriented = e;
    }
  }
  const auto plural = [](int count) { return count == 1 ? "" : "s"; };
  if (boundary) {
    Refuse(fmt::format("it is not closed: {} boundary edge{} (used by one face only), e.g. edge ({}, {}) of face {}",
                       boundary_count, plural(boundary_count), boundary->lo, boundary->hi, boundary->face));
  }
  if (non_manifold) {
    Refuse(fmt::format("it is not manifold: {} edge{} shared by more than two faces, e.g. edge ({}, {}) by {} faces",
                       non_manifold_count, plural(non_manifold_count), non_manifold->lo, non_manifold->hi,
                       non_manifold_faces));
  }
  if (misoriented) {
    Refuse(fmt::format("its faces are not consistently oriented: {} edge{} where both faces run the same way, "
                       "e.g. edge ({}, {})",
                       misoriented_count, plural(misoriented_count), misoriented->lo, misoriented->hi));
  }
}

// Six times the volume enclosed by a closed, consistently oriented surface (divergence theorem).
double SixTimesEnclosedVolume(const Points& vertices, const Faces& faces) {
  double sum = 0.0;
  for (int f = 0; f < faces.rows(); ++f) {
    const Eigen::Vector3d a = vertices.row(faces(f, 0)), b = vertices.row(faces(f, 1)), c = vertices.row(faces(f, 2));
    sum += a.dot(b.cross(c));
  }
  return sum;
}

void CheckSurface(const Points& vertices, const Faces& faces) {
  const Eigen::Index n = vertices.rows();
  if (n < 4) Refuse(fmt::format("it has {} vertices; a closed surface needs at least 4", n));
  if (faces.rows() < 4) Refuse(fmt::format("it has {} faces; a closed surface needs at least 4", faces.rows()));
  for (Eigen::Index v = 0; v < n; ++v) {
    if (!vertices.row(v).allFinite()) Refuse(fmt::format("vertex {} has a non-finite coordinate", v));
  }
  std::vector<char> used(static_cast<size_t>(n), 0);
  for (Eigen::Index f = 0; f < faces.rows(); ++f) {
    for (int k = 0; k < 3; ++k) {
      const int v = faces(f, k);
      if (v < 0 || v >= n) Refuse(fmt::format("face {} refers to vertex {}, out of range [0, {})", f, v, n));
      used[static_cast<size_t>(v)] = 1;
    }
    if (faces(f, 0) == faces(f, 1) || faces(f, 1) == faces(f, 2) || faces(f, 0) == faces(f, 2)) {
      Refuse(fmt::format("face {} repeats a vertex", f));
    }
  }
  // TetGen would merge coinciding vertices (or, with -M, fail on them) and renumber the rest.
  std::vector<int> order(static_cast<size_t>(n));
  std::iota(order.begin(), order.end(), 0);
  const auto position = [&](int v) { return std::tie(vertices(v, 0), vertices(v, 1), vertices(v, 2)); };
  std::sort(order.begin(), order.end(), [&](int a, int b) { return position(a) < position(b); });
  for (size_t i = 1; i < order.size(); ++i) {
    if (position(order[i - 1]) == position(order[i])) {
      Refuse(fmt::format("vertices {} and {} are at the same position", std::min(order[i - 1], order[i]),
                         std::max(order[i - 1], order[i])));
    }
  }
  if (const auto unused = std::find(used.begin(), used.end(), 0); unused != used.end()) {
    Refuse(fmt::format("it has unused vertices (in no face): {}, e.g. vertex {}",
                       std::count(used.begin(), used.end(), 0), unused - used.begin()));
  }
  CheckClosedManifoldOriented(faces);
  const double diagonal = (vertices.colwise().maxCoeff() - vertices.colwise().minCoeff()).norm();
  if (std::abs(SixTimesEnclosedVolume(vertices, faces)) <= 1e-12 * std::pow(diagonal, 3)) {
    Refuse("it encloses no volume (are all its vertices in one plane?)");
  }
}

// ---------------------------------------------------------------------------------------------------------
// What the child sends back: a header, then raw arrays in the parent's own layout (same machine, same binary).

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
std::int64_t PayloadBytes(const MessageHeader& header) {
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

// ---------------------------------------------------------------------------------------------------------
// The child. A fork of a multithreaded process may only call async-signal-safe functions until it execs: any
// lock another thread held at the fork (the allocator's, a stdio stream's) stays locked in the copy. (glibc's
// malloc survives it, sanitizer allocators and many others do not: a forked child running TetGen under ASan
// hung now and then.) So the child is a fresh image of this same executable, started by posix_spawn; a
// constructor in this file sees the variable below before main() runs, runs TetGen and exits. Any program that
// calls Tetrahedralize links this file, so its own executable can always serve as the child.

constexpr const char* kChildVariable = "SPRINGBLEND_TETGEN_CHILD";
constexpr const char* kChildRole = "request=3,result=4";
constexpr int kRequestFd = 3;  // a memfd holding the request, read from offset 0
constexpr int kResultFd = 4;   // the write end of the result pipe

// What the parent sends: this header, the switches, the points (row-major doubles), the faces (row-major int32).
struct Request {
  std::uint64_t magic;
  std::int32_t diagnose;
  std::int32_t switches_bytes;
  std::int64_t points;
  std::int64_t faces;
};
constexpr std::uint64_t kRequestMagic = 0x7370626c74657431ULL;  // "spbltet1"

bool WriteAll(int fd, const void* data, size_t size) {
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

bool ReadAllAt(int fd, void* data, size_t size, off_t offset) {
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

bool SendHeader(int fd, MessageKind kind, std::int32_t error_code = 0) {
  const MessageHeader header{kind, error_code, 0, 0};
  return WriteAll(fd, &header, sizeof(header));
}

// tetgenio frees its arrays with delete[], so they are allocated with new[].
void FillTetGenInput(const std::vector<double>& points, const std::vector<std::int32_t>& faces, tetgenio* in) {
  in->firstnumber = 0;
  in->numberofpoints = static_cast<int>(points.size() / 3);
  in->pointlist = new REAL[points.size()];
  std::copy(points.begin(), points.end(), in->pointlist);
  const int face_count = static_cast<int>(faces.size() / 3);
  in->facetlist = new tetgenio::facet[static_cast<size_t>(face_count)];
  in->numberoffacets = face_count;
  for (int f = 0; f < face_count; ++f) tetgenio::init(&in->facetlist[f]);
  // Markers number the faces from 1 (0 reads as "no marker"), so that the -d report names them.
  in->facetmarkerlist = new int[static_cast<size_t>(face_count)];
  for (int f = 0; f < face_count; ++f) {
    tetgenio::facet& facet = in->facetlist[f];
    facet.polygonlist = new tetgenio::polygon[1];
    tetgenio::init(&facet.polygonlist[0]);
    facet.numberofpolygons = 1;
    const size_t first = 3 * static_cast<size_t>(f);
    facet.polygonlist[0].vertexlist = new int[3]{faces[first], faces[first + 1], faces[first + 2]};
    facet.polygonlist[0].numberofvertices = 3;
    in->facetmarkerlist[f] = f + 1;
  }
}

bool SendMesh(tetgenio* in, char* switches, int fd) {
  tetgenio out;
  tetrahedralize(switches, in, &out);
  static_assert(sizeof(int) == sizeof(std::int32_t));
  const MessageHeader header{MessageKind::kMesh, 0, out.numberofpoints, out.numberoftetrahedra};
  return WriteAll(fd, &header, sizeof(header)) &&
         WriteAll(fd, out.pointlist, sizeof(double) * 3 * static_cast<size_t>(out.numberofpoints)) &&
         WriteAll(fd, out.tetrahedronlist, sizeof(int) * 4 * static_cast<size_t>(out.numberoftetrahedra));
}

// TetGen -d prints each intersecting pair as "  Facet #a intersects facet #b ..." (or "duplicates"), with the
// facet markers, and may find a pair more than once. Returns the distinct pairs as 0-based face indices.
std::vector<std::array<std::int32_t, 2>> ParseIntersections(const std::string& log) {
  std::vector<std::array<std::int32_t, 2>> pairs;
  for (size_t begin = 0; begin < log.size();) {
    const size_t end = std::min(log.find('\n', begin), log.size());
    const std::string line = log.substr(begin, end - begin);
    begin = end + 1;
    int a = 0, b = 0;
    char verb[16] = {};
    if (std::sscanf(line.c_str(), " Facet #%d %15s facet #%d", &a, verb, &b) == 3 &&
        (std::strcmp(verb, "intersects") == 0 || std::strcmp(verb, "duplicates") == 0)) {
      pairs.push_back({std::min(a, b) - 1, std::max(a, b) - 1});
    }
  }
  std::sort(pairs.begin(), pairs.end());
  pairs.erase(std::unique(pairs.begin(), pairs.end()), pairs.end());
  return pairs;
}

bool SendIntersections(tetgenio* in, char* switches, int fd) {
  // The -d report goes to stdout only: catch it in memory.
  char* log = nullptr;
  size_t log_size = 0;
  FILE* memory = open_memstream(&log, &log_size);
  if (memory == nullptr) return false;
  stdout = memory;
  tetgenio out;
  tetrahedralize(switches, in, &out);
  std::fflush(memory);
  const auto pairs = ParseIntersections(std::string(log, log_size));
  const MessageHeader header{MessageKind::kIntersections, 0, 0, static_cast<std::int64_t>(pairs.size())};
  return WriteAll(fd, &header, sizeof(header)) && WriteAll(fd, pairs.data(), sizeof(pairs[0]) * pairs.size());
}

// Reads the request, runs TetGen, sends the message; returns the exit code.
int ServeChild() {
  Request request{};
  if (!ReadAllAt(kRequestFd, &request, sizeof(request), 0) || request.magic != kRequestMagic ||
      request.switches_bytes <= 0 || request.switches_bytes > 256 || request.points < 0 || request.faces < 0 ||
      request.points > std::numeric_limits<std::int32_t>::max() ||
      request.faces > std::numeric_limits<std::int32_t>::max()) {
    return 2;
  }
  bool sent = false;
  try {
    std::string switches(static_cast<size_t>(request.switches_bytes), '\0');
    std::vector<double> points(3 * static_cast<size_t>(request.points));
    std::vector<std::int32_t> faces(3 * static_cast<size_t>(request.faces));
    off_t offset = sizeof(request);
    if (!ReadAllAt(kRequestFd, switches.data(), switches.size(), offset)) return 2;
    offset += static_cast<off_t>(switches.size());
    if (!ReadAllAt(kRequestFd, points.data(), sizeof(double) * points.size(), offset)) return 2;
    offset += static_cast<off_t>(sizeof(double) * points.size());
    if (!ReadAllAt(kRequestFd, faces.data(), sizeof(std::int32_t) * faces.size(), offset)) return 2;
    close(kRequestFd);
    tetgenio in;
    FillTetGenInput(points, faces, &in);
    sent = request.diagnose != 0 ? SendIntersections(&in, switches.data(), kResultFd)
                                 : SendMesh(&in, switches.data(), kResultFd);
  } catch (int code) {  // TetGen's terminatetetgen()
    sent = SendHeader(kResultFd, MessageKind::kTetGenError, code);
  } catch (const std::bad_alloc&) {
    sent = SendHeader(kResultFd, MessageKind::kOutOfMemory);
  } catch (...) {
    sent = SendHeader(kResultFd, MessageKind::kUnknownException);
  }
  return sent ? 0 : 1;
}

// Runs before main() in every program that links this file; in anything but a TetGen child it only reads one
// variable. _exit: no atexit handlers, no static destructors, no sanitizer leak report of the parent's objects.
__attribute__((constructor)) void ServeChildIfAsked() {
  const char* role = std::getenv(kChildVariable);
  if (role == nullptr || std::strcmp(role, kChildRole) != 0) return;
  _exit(ServeChild());
}

// ---------------------------------------------------------------------------------------------------------
// The parent side.

struct ChildOutcome {
  bool timed_out = false;
  bool complete = false;  // a whole message arrived
  MessageHeader header{};
  std::vector<char> payload;
  std::optional<int> wait_status;  // empty if it could not be collected
};

// Owns a started child: however the parent leaves, the read end is closed and the child killed and reaped.
class Child {
 public:
  Child(pid_t pid, int fd) : pid_(pid), fd_(fd) {}
  Child(const Child&) = delete;
  Child& operator=(const Child&) = delete;
  ~Child() {
    if (pid_ > 0) Reap(true);
  }

  int fd() const { return fd_; }

  std::optional<int> Reap(bool kill_first) {
    close(fd_);
    if (kill_first) kill(pid_, SIGKILL);
    int status = 0;
    pid_t reaped;
    do {
      reaped = waitpid(pid_, &status, 0);
    } while (reaped < 0 && errno == EINTR);
    pid_ = -1;
    if (reaped < 0) return std::nullopt;  // e.g. the caller set SIGCHLD to SIG_IGN
    return status;
  }

 private:
  pid_t pid_;
  int fd_;
};

std::string SystemError(const char* call, int error) {
  return fmt::format("{} failed: {}", call, std::generic_category().message(error));
}

std::string SystemError(const char* call) { return SystemError(call, errno); }

// Closes a descriptor when it goes out of scope.
class Descriptor {
 public:
  explicit Descriptor(int fd = -1) : fd_(fd) {}
  Descriptor(const Descriptor&) = delete;
  Descriptor& operator=(const Descriptor&) = delete;
  Descriptor(Descriptor&& other) noexcept : fd_(other.Release()) {}
  ~Descriptor() { Reset(); }
  int get() const { return fd_; }
  int Release() { return std::exchange(fd_, -1); }
  void Reset(int fd = -1) {
    if (fd_ >= 0) close(fd_);
    fd_ = fd;
  }

 private:
  int fd_;
};

[[noreturn]] void CannotStart(const std::string& reason) {
  throw ToError(TetGenFailed("could not be started: " + reason));
}

// The request as an anonymous in-memory file (no pipe to fill, no SIGPIPE if the child dies early).
Descriptor WriteRequest(const Points& vertices, const Faces& faces, const std::string& switches, bool diagnose) {
  Descriptor request(memfd_create("springblend-tetgen-request", MFD_CLOEXEC));
  if (request.get() < 0) CannotStart(SystemError("memfd_create"));
  const Request header{kRequestMagic, diagnose ? 1 : 0, static_cast<std::int32_t>(switches.size()), vertices.rows(),
                       faces.rows()};
  static_assert(sizeof(int) == sizeof(std::int32_t));
  if (!WriteAll(request.get(), &header, sizeof(header)) ||
      !WriteAll(request.get(), switches.data(), switches.size()) ||
      !WriteAll(request.get(), vertices.data(), sizeof(double) * static_cast<size_t>(vertices.size())) ||
      !WriteAll(request.get(), faces.data(), sizeof(int) * static_cast<size_t>(faces.size()))) {
    CannotStart(SystemError("writing the request"));
  }
  return request;
}

// A copy of `fd` numbered above the descriptors the child gets, so that setting those up cannot clobber it.
Descriptor HighCopy(int fd) {
  Descriptor copy(fcntl(fd, F_DUPFD_CLOEXEC, kResultFd + 1));
  if (copy.get() < 0) CannotStart(SystemError("fcntl(F_DUPFD_CLOEXEC)"));
  return copy;
}

// Starts this executable as a TetGen child reading `request` and writing to `result`; returns its pid.
pid_t SpawnChild(int request, int result) {
  posix_spawn_file_actions_t actions;
  posix_spawnattr_t attributes;
  if (int error = posix_spawn_file_actions_init(&actions); error != 0) {
    CannotStart(SystemError("posix_spawn_file_actions_init", error));
  }
  if (int error = posix_spawnattr_init(&attributes); error != 0) {
    posix_spawn_file_actions_destroy(&actions);
    CannotStart(SystemError("posix_spawnattr_init", error));
  }
  // Default dispositions and an empty mask for every signal (the caller may block SIGTERM for a signal thread,
  // or have set SIGPIPE to be ignored); standard streams on /dev/null (TetGen prints); nothing else inherited.
  sigset_t all, none;
  sigfillset(&all);
  sigemptyset(&none);
  int error = posix_spawnattr_setsigdefault(&attributes, &all);
  if (error == 0) error = posix_spawnattr_setsigmask(&attributes, &none);
  if (error == 0) error = posix_spawnattr_setflags(&attributes, POSIX_SPAWN_SETSIGDEF | POSIX_SPAWN_SETSIGMASK);
  if (error == 0) error = posix_spawn_file_actions_addopen(&actions, STDIN_FILENO, "/dev/null", O_RDONLY, 0);
  if (error == 0) error = posix_spawn_file_actions_addopen(&actions, STDOUT_FILENO, "/dev/null", O_WRONLY, 0);
  if (error == 0) error = posix_spawn_file_actions_adddup2(&actions, STDOUT_FILENO, STDERR_FILENO);
  if (error == 0) error = posix_spawn_file_actions_adddup2(&actions, request, kRequestFd);
  if (error == 0) error = posix_spawn_file_actions_adddup2(&actions, result, kResultFd);
  if (error == 0) error = posix_spawn_file_actions_addclosefrom_np(&actions, kResultFd + 1);

  // The environment plus the role; an inherited role (this process being a child itself) is replaced.
  const std::string role = fmt::format("{}={}", kChildVariable, kChildRole);
  std::vector<char*> environment;
  const std::string prefix = fmt::format("{}=", kChildVariable);
  for (char** variable = environ; *variable != nullptr; ++variable) {
    if (std::strncmp(*variable, prefix.c_str(), prefix.size()) != 0) environment.push_back(*variable);
  }
  environment.push_back(const_cast<char*>(role.c_str()));
  environment.push_back(nullptr);
  char name[] = "springblend-tetgen";
  char* arguments[] = {name, nullptr};

  pid_t pid = -1;
  if (error == 0) error = posix_spawn(&pid, "/proc/self/exe", &actions, &attributes, arguments, environment.data());
  posix_spawn_file_actions_destroy(&actions);
  posix_spawnattr_destroy(&attributes);
  if (error != 0) CannotStart(SystemError("posix_spawn of /proc/self/exe", error));
  return pid;
}

// Runs TetGen with `switches` in a child and collects its message; kills the child at `deadline`.
ChildOutcome RunInChild(const Points& vertices, const Faces& faces, const std::string& switches, bool diagnose,
                        Clock::time_point deadline) {
  Descriptor request = WriteRequest(vertices, faces, switches, diagnose);
  Descriptor high_request = HighCopy(request.get());
  request.Reset();
  int fds[2];
  // Close-on-exec keeps the pipe out of programs that other threads spawn meanwhile.
  if (pipe2(fds, O_CLOEXEC) != 0) CannotStart(SystemError("pipe2"));
  Descriptor read_end(fds[0]), write_end(fds[1]);
  Descriptor high_write_end = HighCopy(write_end.get());
  write_end.Reset();
  const pid_t pid = SpawnChild(high_request.get(), high_write_end.get());
  // Only the child holds the write end now: its exit is the end of file.
  high_write_end.Reset();
  high_request.Reset();
  Child child(pid, read_end.Release());

  // Read while the child writes, so that a result larger than the pipe's buffer cannot block it.
  ChildOutcome outcome;
  std::vector<char> buffer(sizeof(MessageHeader));
  size_t received = 0;
  bool have_header = false;
  while (received < buffer.size()) {
    const auto left = std::chrono::ceil<std::chrono::milliseconds>(deadline - Clock::now()).count();
    if (left <= 0) {
      outcome.timed_out = true;
      break;
    }
    pollfd ready{child.fd(), POLLIN, 0};
    const int polled = poll(&ready, 1, static_cast<int>(std::min<decltype(left)>(left, 1 << 30)));
    if (polled == 0 || (polled < 0 && errno == EINTR)) continue;
    if (polled < 0) break;
    const ssize_t got = read(child.fd(), buffer.data() + received, buffer.size() - received);
    if (got == 0) break;  // end of file: the child is gone
    if (got < 0) {
      if (errno == EINTR || errno == EAGAIN) continue;
      break;
    }
    received += static_cast<size_t>(got);
    if (!have_header && received == sizeof(MessageHeader)) {
      std::memcpy(&outcome.header, buffer.data(), sizeof(MessageHeader));
      const std::int64_t payload = PayloadBytes(outcome.header);
      if (payload < 0) break;
      have_header = true;
      buffer.resize(sizeof(MessageHeader) + static_cast<size_t>(payload));
    }
  }
  outcome.complete = have_header && received == buffer.size();
  // After a complete message the child only has to _exit; otherwise it may still be running.
  outcome.wait_status = child.Reap(!outcome.complete);
  if (outcome.complete) outcome.payload.assign(buffer.begin() + sizeof(MessageHeader), buffer.end());
  return outcome;
}

std::string SignalName(int signal_number) {
  const char* abbreviation = sigabbrev_np(signal_number);
  return abbreviation != nullptr ? fmt::format("SIG{}", abbreviation) : fmt::format("signal {}", signal_number);
}

// Why a run that ended in time delivered no mesh.
Failure DescribeFailure(const ChildOutcome& run) {
  if (!run.complete) {
    if (!run.wait_status) return TetGenFailed("ended without a result");
    if (WIFSIGNALED(*run.wait_status)) return TetGenFailed("crashed with " + SignalName(WTERMSIG(*run.wait_status)));
    return TetGenFailed(fmt::format("exited with code {} without a result", WEXITSTATUS(*run.wait_status)));
  }
  switch (run.header.kind) {
    case MessageKind::kTetGenError:
      // The codes of TetGen 1.5's terminatetetgen(). 3 to 5 and 10 are about the input.
      switch (run.header.error_code) {
        case 1:
          return TetGenFailed("ran out of memory (error 1)");
        case 2:
          return TetGenFailed("had an internal error (error 2)");
        case 3:
          return {ErrorCode::kInvalidInput, "TetGen found a self-intersection (error 3)"};
        case 4:
          return {ErrorCode::kInvalidInput,
                  "TetGen found features below its tolerance, e.g. a vertex almost on a face it does not belong to "
                  "(error 4)"};
        case 5:
          return {ErrorCode::kInvalidInput, "TetGen found two almost coincident faces (error 5)"};
        case 10:
          return {ErrorCode::kInvalidInput, "TetGen rejected the input (error 10)"};
        default:
          return TetGenFailed(fmt::format("stopped with error {}", run.header.error_code));
      }
    case MessageKind::kOutOfMemory:
      return TetGenFailed("ran out of memory");
    case MessageKind::kUnknownException:
      return TetGenFailed("threw an unexpected exception");
    case MessageKind::kMesh:
    case MessageKind::kIntersections:
      break;
  }
  return {ErrorCode::kInternal, "TetGen's process sent an unexpected message"};
}

// ---------------------------------------------------------------------------------------------------------
// Input, and reading and checking the result.

TetMesh ReadMesh(const ChildOutcome& run, int surface_vertices) {
  TetMesh mesh;
  mesh.surface_vertices = surface_vertices;
  mesh.vertices.resize(run.header.points, 3);
  mesh.tets.resize(run.header.count, 4);
  const size_t point_bytes = sizeof(double) * static_cast<size_t>(mesh.vertices.size());
  std::memcpy(mesh.vertices.data(), run.payload.data(), point_bytes);
  std::memcpy(mesh.tets.data(), run.payload.data() + point_bytes, sizeof(int) * static_cast<size_t>(mesh.tets.size()));
  return mesh;
}

double SixTimesVolume(const Points& v, int a, int b, int c, int d) {
  const Eigen::RowVector3d pa = v.row(a);
  return (v.row(b) - pa).dot((v.row(c) - pa).cross(v.row(d) - pa));
}

// TetGen's tets all have one orientation; makes it the positive one.
std::optional<Failure> OrientPositively(TetMesh* mesh) {
  Eigen::Index positive = 0, negative = 0;
  for (Eigen::Index t = 0; t < mesh->tets.rows(); ++t) {
    const auto tet = mesh->tets.row(t);
    const double volume = SixTimesVolume(mesh->vertices, tet[0], tet[1], tet[2], tet[3]);
    positive += volume > 0.0;
    negative += volume < 0.0;
  }
  const Eigen::Index count = mesh->tets.rows();
  if (negative == count) {
    const Eigen::VectorXi first = mesh->tets.col(0);
    mesh->tets.col(0) = mesh->tets.col(1);
    mesh->tets.col(1) = first;
  } else if (positive != count) {
    return TetGenFailed(fmt::format("returned {} tetrahedra of mixed orientation ({} positive, {} negative, {} flat)",
                                    count, positive, negative, count - positive - negative));
  }
  return std::nullopt;
}

// Every input face must be a face of exactly one tet (the one inside).
std::optional<Failure> CheckSurfaceKept(const Faces& faces, const TetMesh& mesh) {
  std::vector<std::pair<Triangle, int>> surface;
  surface.reserve(static_cast<size_t>(faces.rows()));
  for (int f = 0; f < faces.rows(); ++f) {
    Triangle key{faces(f, 0), faces(f, 1), faces(f, 2)};
    std::sort(key.begin(), key.end());
    surface.emplace_back(key, f);
  }
  std::sort(surface.begin(), surface.end());
  std::vector<int> hits(static_cast<size_t>(faces.rows()), 0);
  for (Eigen::Index t = 0; t < mesh.tets.rows(); ++t) {
    for (int skip = 0; skip < 4; ++skip) {
      Triangle key;
      for (int k = 0, j = 0; k < 4; ++k) {
        if (k != skip) key[j++] = mesh.tets(t, k);
      }
      if (std::max({key[0], key[1], key[2]}) >= mesh.surface_vertices) continue;
      std::sort(key.begin(), key.end());
      const auto found = std::lower_bound(surface.begin(), surface.end(), std::make_pair(key, -1));
      if (found != surface.end() && found->first == key) ++hits[static_cast<size_t>(found->second)];
    }
  }
  for (size_t f = 0; f < hits.size(); ++f) {
    if (hits[f] != 1) {
      return TetGenFailed(
          fmt::format("did not keep the surface: input face {} is a face of {} tetrahedra, not 1", f, hits[f]));
    }
  }
  return std::nullopt;
}

// The contract of Tetrahedralize: surface vertices first and unchanged, valid indices, positive volumes, every
// surface triangle kept.
std::optional<Failure> CheckAndOrient(const Points& vertices, const Faces& faces, TetMesh* mesh) {
  const Eigen::Index n = vertices.rows();
  if (mesh->vertices.rows() < n) {
    return TetGenFailed(
        fmt::format("returned {} vertices, fewer than the {} of the surface", mesh->vertices.rows(), n));
  }
  for (Eigen::Index v = 0; v < n; ++v) {
    if (mesh->vertices.row(v) != vertices.row(v)) {
      return TetGenFailed(fmt::format("moved or renumbered the surface vertices (vertex {} differs)", v));
    }
  }
  if (mesh->tets.rows() == 0) return TetGenFailed("returned no tetrahedra");
  if ((mesh->tets.array() < 0).any() || (mesh->tets.array() >= mesh->vertices.rows()).any()) {
    return TetGenFailed("returned a tetrahedron with a vertex index out of range");
  }
  if (auto failure = OrientPositively(mesh)) return failure;
  return CheckSurfaceKept(faces, *mesh);
}

std::string MeshingSwitches(const TetrahedralizeOptions& options) {
  // p: the input is a surface; Y: no Steiner points on it; M: no merging of coplanar neighbouring faces or of
  // close vertices (either would change the input triangles); q: the quality bound (TetGen reads it without an
  // exponent); Q: quiet.
  std::string switches = fmt::format("pYMq{:.6f}", options.radius_edge_ratio);
  if (options.max_volume > 0.0) switches += fmt::format("a{:.17g}", options.max_volume);
  if (options.max_steiner_points >= 0) switches += fmt::format("S{}", options.max_steiner_points);
  return switches + "Q";
}

}  // namespace

TetMesh Tetrahedralize(const Points& vertices, const Faces& faces, const TetrahedralizeOptions& options) {
  CheckOptions(options);
  CheckSurface(vertices, faces);
  // Far-off deadlines are capped so that the time arithmetic cannot overflow.
  const auto timeout = std::chrono::duration<double>(std::min(options.timeout_seconds, 1e8));
  const Clock::time_point deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(timeout);

  const ChildOutcome run = RunInChild(vertices, faces, MeshingSwitches(options), false, deadline);
  if (run.timed_out) {
    throw ToError(TetGenFailed(fmt::format(
        "timed out: no result within {} s (timeout_seconds), its process was killed", options.timeout_seconds)));
  }
  std::optional<Failure> failure;
  if (run.complete && run.header.kind == MessageKind::kMesh) {
    TetMesh mesh = ReadMesh(run, static_cast<int>(vertices.rows()));
    failure = CheckAndOrient(vertices, faces, &mesh);
    if (!failure) return mesh;
  } else {
    failure = DescribeFailure(run);
  }
  // The checks before the run cannot see self-intersections, the usual reason why TetGen fails on a closed
  // surface. Its -d check finds them; it gets what is left of the time.
  const ChildOutcome diagnosis = RunInChild(vertices, faces, "pd", true, deadline);
  if (diagnosis.complete && diagnosis.header.kind == MessageKind::kIntersections && diagnosis.header.count > 0) {
    std::array<std::int32_t, 2> example;
    std::memcpy(example.data(), diagnosis.payload.data(), sizeof(example));
    Refuse(fmt::format("it intersects itself ({} pairs of faces, e.g. faces {} and {}); {}", diagnosis.header.count,
                       example[0], example[1], failure->what));
  }
  throw ToError(*failure);
}

}  // namespace springblend::internal
