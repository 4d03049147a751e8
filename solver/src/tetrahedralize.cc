// TetGen 1.5 ends a failed run by throwing an int (or, built without TETLIBRARY, by exit()), can crash or loop
// forever on bad input, and prints to stdout. So it never runs in the caller's process: a forked child runs it
// and sends the result back through a pipe as raw arrays; the parent reads it under a deadline, reaps the
// child and turns every way the child can end into an Error.
#include "tetrahedralize.h"

#include <Eigen/Geometry>
#include <fcntl.h>
#include <fmt/format.h>
#include <poll.h>
#include <signal.h>
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
// The child. It runs in a copy of a possibly multithreaded process, so it uses only TetGen, malloc (which glibc
// makes safe after fork) and fresh stdio streams: a stream such as stdout may have been locked by another
// thread at the moment of the fork, and that lock would never be released here.

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

bool SendHeader(int fd, MessageKind kind, std::int32_t error_code = 0) {
  const MessageHeader header{kind, error_code, 0, 0};
  return WriteAll(fd, &header, sizeof(header));
}

// Detaches the child from the caller's process state; returns the descriptor to write the result to.
int IsolateChild(int result_fd) {
  // A crash handler the caller installed must not run here: a crash should simply end the child.
  struct sigaction default_action {};
  default_action.sa_handler = SIG_DFL;
  for (const int signal_number : {SIGSEGV, SIGBUS, SIGFPE, SIGILL, SIGABRT, SIGPIPE}) {
    sigaction(signal_number, &default_action, nullptr);
  }
  if (result_fd <= STDERR_FILENO) result_fd = fcntl(result_fd, F_DUPFD, STDERR_FILENO + 1);
  const int null_fd = open("/dev/null", O_RDWR);
  for (const int fd : {STDIN_FILENO, STDOUT_FILENO, STDERR_FILENO}) dup2(null_fd, fd);
  // Close every other inherited descriptor, above all the pipes of concurrent calls in other threads: their
  // readers would not see end-of-file while this child holds a copy of the write end.
  if (result_fd > STDERR_FILENO + 1) close_range(STDERR_FILENO + 1, static_cast<unsigned>(result_fd) - 1, 0);
  close_range(static_cast<unsigned>(result_fd) + 1, ~0U, 0);
  return result_fd;
}

bool SendMesh(tetgenio* in, char* switches, int fd) {
  stdout = std::fopen("/dev/null", "w");
  if (stdout == nullptr) return false;
  stderr = stdout;
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
  stdout = open_memstream(&log, &log_size);
  if (stdout == nullptr) return false;
  stderr = stdout;
  tetgenio out;
  tetrahedralize(switches, in, &out);
  std::fflush(stdout);
  const auto pairs = ParseIntersections(std::string(log, log_size));
  const MessageHeader header{MessageKind::kIntersections, 0, 0, static_cast<std::int64_t>(pairs.size())};
  return WriteAll(fd, &header, sizeof(header)) && WriteAll(fd, pairs.data(), sizeof(pairs[0]) * pairs.size());
}

[[noreturn]] void RunChild(int result_fd, tetgenio* in, char* switches, bool diagnose) {
  const int fd = IsolateChild(result_fd);
  bool sent = false;
  try {
    sent = diagnose ? SendIntersections(in, switches, fd) : SendMesh(in, switches, fd);
  } catch (int code) {  // TetGen's terminatetetgen()
    sent = SendHeader(fd, MessageKind::kTetGenError, code);
  } catch (const std::bad_alloc&) {
    sent = SendHeader(fd, MessageKind::kOutOfMemory);
  } catch (...) {
    sent = SendHeader(fd, MessageKind::kUnknownException);
  }
  // _exit: no atexit handlers, no flushing of the caller's stdio buffers copied into this process.
  _exit(sent ? 0 : 1);
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

std::string SystemError(const char* call) {
  return fmt::format("{} failed: {}", call, std::generic_category().message(errno));
}

// Runs TetGen with `switches` in a child and collects its message; kills the child at `deadline`.
ChildOutcome RunInChild(tetgenio* in, std::string switches, bool diagnose, Clock::time_point deadline) {
  int fds[2];
  // Close-on-exec keeps the pipe out of programs that other threads spawn meanwhile.
  if (pipe2(fds, O_CLOEXEC) != 0) throw ToError(TetGenFailed("could not be started: " + SystemError("pipe2")));
  const pid_t pid = fork();
  if (pid < 0) {
    const std::string reason = SystemError("fork");
    close(fds[0]);
    close(fds[1]);
    throw ToError(TetGenFailed("could not be started: " + reason));
  }
  if (pid == 0) {
    close(fds[0]);
    RunChild(fds[1], in, switches.data(), diagnose);
  }
  close(fds[1]);
  Child child(pid, fds[0]);

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

// tetgenio frees its arrays with delete[], so they are allocated with new[].
void FillTetGenInput(const Points& vertices, const Faces& faces, tetgenio* in) {
  in->firstnumber = 0;
  in->numberofpoints = static_cast<int>(vertices.rows());
  in->pointlist = new REAL[static_cast<size_t>(vertices.size())];
  std::copy(vertices.data(), vertices.data() + vertices.size(), in->pointlist);
  in->facetlist = new tetgenio::facet[static_cast<size_t>(faces.rows())];
  in->numberoffacets = static_cast<int>(faces.rows());
  for (int f = 0; f < faces.rows(); ++f) tetgenio::init(&in->facetlist[f]);
  // Markers number the faces from 1 (0 reads as "no marker"), so that the -d report names them.
  in->facetmarkerlist = new int[static_cast<size_t>(faces.rows())];
  for (int f = 0; f < faces.rows(); ++f) {
    tetgenio::facet& facet = in->facetlist[f];
    facet.polygonlist = new tetgenio::polygon[1];
    tetgenio::init(&facet.polygonlist[0]);
    facet.numberofpolygons = 1;
    facet.polygonlist[0].vertexlist = new int[3]{faces(f, 0), faces(f, 1), faces(f, 2)};
    facet.polygonlist[0].numberofvertices = 3;
    in->facetmarkerlist[f] = f + 1;
  }
}

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
  tetgenio in;
  FillTetGenInput(vertices, faces, &in);
  // Far-off deadlines are capped so that the time arithmetic cannot overflow.
  const auto timeout = std::chrono::duration<double>(std::min(options.timeout_seconds, 1e8));
  const Clock::time_point deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(timeout);

  const ChildOutcome run = RunInChild(&in, MeshingSwitches(options), false, deadline);
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
  const ChildOutcome diagnosis = RunInChild(&in, "pd", true, deadline);
  if (diagnosis.complete && diagnosis.header.kind == MessageKind::kIntersections && diagnosis.header.count > 0) {
    std::array<std::int32_t, 2> example;
    std::memcpy(example.data(), diagnosis.payload.data(), sizeof(example));
    Refuse(fmt::format("it intersects itself ({} pairs of faces, e.g. faces {} and {}); {}", diagnosis.header.count,
                       example[0], example[1], failure->what));
  }
  throw ToError(*failure);
}

}  // namespace springblend::internal
