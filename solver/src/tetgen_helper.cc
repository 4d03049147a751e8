// springblend-tetgen: the helper process in which the solver runs TetGen 1.5 (see tetgen_process.h for why a
// separate process). It reads one request from descriptor 3, converts it to TetGen's input, runs TetGen and
// writes one message to descriptor 4 (tetgen_protocol.h). It dies with the process that started it and has a
// CPU limit of its own, so neither a parent killed with -9 nor a TetGen loop leaves it running.
// Not meant to be run by hand: the solver finds it next to the running program or in ../libexec/springblend.
#include <sys/prctl.h>
#include <sys/resource.h>
#include <tetgen.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <csignal>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <new>
#include <string>
#include <vector>

#include "tetgen_protocol.h"

namespace springblend::internal::tetgen {
namespace {

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

// The soft limit sends SIGXCPU, the hard one a second later SIGKILL.
void LimitCpu(std::int64_t seconds) {
  if (seconds <= 0) return;
  const rlimit limit{static_cast<rlim_t>(seconds), static_cast<rlim_t>(seconds) + 1};
  setrlimit(RLIMIT_CPU, &limit);
}

// Reads the request, runs TetGen, sends the message; returns the exit code.
int Serve() {
  // Die with the parent (a SIGKILL when it goes), first thing; and serve only the parent the request names: if
  // it died between the spawn and the prctl, this process already belongs to someone else and must not run.
  if (prctl(PR_SET_PDEATHSIG, SIGKILL) != 0) return 3;
  Request request{};
  if (!ReadAllAt(kRequestFd, &request, sizeof(request), 0) || request.magic != kRequestMagic ||
      request.switches_bytes < 0 || request.switches_bytes > 256 || request.points < 0 || request.faces < 0 ||
      request.points > std::numeric_limits<std::int32_t>::max() ||
      request.faces > std::numeric_limits<std::int32_t>::max()) {
    return 2;
  }
  if (static_cast<std::int64_t>(getppid()) != request.parent) return 3;
  LimitCpu(request.cpu_seconds);
  if (request.task == Task::kHold) {
    for (;;) pause();
  }
  if (request.task == Task::kSpin) {
    volatile std::uint64_t spins = 0;
    for (;;) spins = spins + 1;
  }
  if (request.switches_bytes == 0) return 2;
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
    sent = request.task == Task::kDiagnose ? SendIntersections(&in, switches.data(), kResultFd)
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

}  // namespace
}  // namespace springblend::internal::tetgen

int main(int argc, char** argv) {
  if (argc != 2 || std::strcmp(argv[1], "--serve") != 0) {
    std::fprintf(stderr,
                 "springblend-tetgen: the solver's TetGen helper; it is started by springblend programs, which "
                 "pass it a request on descriptor 3 (usage: springblend-tetgen --serve 3<REQUEST 4>RESULT)\n");
    return 2;
  }
  // _exit: no atexit handlers or static destructors, and no sanitizer leak report for what TetGen left.
  _exit(springblend::internal::tetgen::Serve());
}
