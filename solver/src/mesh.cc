#include "springblend/mesh.h"

#include <OpenMesh/Core/IO/IOManager.hh>
#include <OpenMesh/Core/IO/importer/ImporterT.hh>
#include <OpenMesh/Core/Mesh/PolyMesh_ArrayKernelT.hh>
#include <OpenMesh/Core/System/omstream.hh>
#include <fmt/format.h>
#include <fmt/os.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <charconv>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <mutex>
#include <sstream>
#include <string_view>
#include <vector>

#include "off_reader.h"
#include "springblend/error.h"

namespace springblend {
namespace {

struct DoubleTraits : public OpenMesh::DefaultTraits {
  using Point = OpenMesh::Vec3d;
};
using PolyMesh = OpenMesh::PolyMesh_ArrayKernelT<DoubleTraits>;

// OpenMesh's importer builds a half-edge mesh, which splits non-manifold faces onto duplicated vertices
// and drops faces with repeated corners. A rig needs the file exactly as written, so this importer
// records the raw vertex and face lists as the reader reports them and lets OpenMesh carry on.
class RawImporter final : public OpenMesh::IO::ImporterT<PolyMesh> {
 public:
  explicit RawImporter(PolyMesh& mesh) : ImporterT<PolyMesh>(mesh) {}

  OpenMesh::VertexHandle add_vertex(const OpenMesh::Vec3f& p) override {
    soup.points.push_back({p[0], p[1], p[2]});
    return ImporterT<PolyMesh>::add_vertex(p);
  }
  OpenMesh::VertexHandle add_vertex(const OpenMesh::Vec3d& p) override {
    soup.points.push_back({p[0], p[1], p[2]});
    return ImporterT<PolyMesh>::add_vertex(p);
  }
  // The PLY reader adds a vertex first and sets its position afterwards.
  OpenMesh::VertexHandle add_vertex() override {
    soup.points.push_back({0.0, 0.0, 0.0});
    return ImporterT<PolyMesh>::add_vertex();
  }
  void set_point(OpenMesh::VertexHandle vh, const OpenMesh::Vec3f& p) override {
    if (vh.idx() >= 0 && static_cast<size_t>(vh.idx()) < soup.points.size()) {
      soup.points[vh.idx()] = {p[0], p[1], p[2]};
    }
    ImporterT<PolyMesh>::set_point(vh, p);
  }
  OpenMesh::FaceHandle add_face(const VHandles& indices) override {
    std::vector<int> face;
    face.reserve(indices.size());
    for (const auto& vh : indices) face.push_back(vh.idx());
    soup.polygons.push_back(std::move(face));
    return ImporterT<PolyMesh>::add_face(indices);
  }

  PolygonSoup soup;
};

void QuietOpenMesh() {
  static std::once_flag once;
  std::call_once(once, [] {
    // springblend reports problems itself, naming the file and element; OpenMesh's own console
    // chatter about the same faces would only confuse.
    ::omerr().disable();
    ::omlog().disable();
    ::omout().disable();
  });
}

std::string Lowercase(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return std::tolower(c); });
  return s;
}

// OpenMesh 9.0's PLY reader trusts its header: it reads it word by word until the word end_header, and a word it
// cannot parse as the number it expects (a version, a count), or the end of the file, makes it loop for ever;
// garbled headers crash it. The header is checked here first, strictly and line by line, so a bad file gets an
// error naming the line and never reaches that reader; `obj_info` lines, whose words OpenMesh would read as
// keywords, become comments. Returns the text to hand to OpenMesh. (Its OFF reader trusted the counts as well;
// OFF has a reader of its own, off_reader.cc.)
std::string CheckPly(std::string text, const std::string& source) {
  constexpr size_t kMaxHeader = 1 << 16;
  const auto fail = [&](const std::string& what) {
    throw Error(ErrorCode::kInvalidInput, fmt::format("{}: PLY header: {}", source, what));
  };
  const auto trimmed = [](std::string_view line) {
    const size_t first = line.find_first_not_of(" \t\r\v\f");
    if (first == std::string_view::npos) return std::string_view();
    return line.substr(first, line.find_last_not_of(" \t\r\v\f") - first + 1);
  };
  // The header ends at the first line that is end_header alone (not at those letters in a comment).
  size_t end = std::string::npos, body = text.size();
  for (size_t at = 0; at < text.size() && at <= kMaxHeader;) {
    const size_t eol = std::min(text.find('\n', at), text.size());
    if (trimmed(std::string_view(text).substr(at, eol - at)) == "end_header") {
      end = at;
      body = std::min(eol + 1, text.size());
      break;
    }
    at = eol + 1;
  }
  if (end == std::string::npos) fail("no end_header line in the first 64 KiB");
  const size_t body_bytes = text.size() - body;
  std::istringstream header(text.substr(0, end));
  std::string line;
  int number = 0;
  size_t line_start = 0;
  bool format = false;
  bool element = false;
  static const std::vector<std::string> kTypes = {"char",  "uchar", "short",  "ushort",  "int",    "uint",
                                                  "float", "double", "int8",  "uint8",   "int16",  "uint16",
                                                  "int32", "uint32", "float32", "float64"};
  const auto known_type = [&](const std::string& t) {
    return std::find(kTypes.begin(), kTypes.end(), t) != kTypes.end();
  };
  const auto digits = [](std::string_view t) {
    return !t.empty() && std::all_of(t.begin(), t.end(), [](unsigned char c) { return std::isdigit(c); });
  };
  for (; std::getline(header, line); line_start += line.size() + 1) {
    ++number;
    std::istringstream split(line);
    std::vector<std::string> w;
    for (std::string word; split >> word;) w.push_back(word);
    if (number == 1) {
      if (w.size() != 1 || w[0] != "ply") fail("the first line is not 'ply'");
      continue;
    }
    if (w.empty()) continue;
    if (!format && w[0] != "format") fail(fmt::format("line {}: the format line must come first", number));
    if (w[0] == "comment") continue;
    if (w[0] == "obj_info") {
      text.replace(line_start + line.find("obj_info"), 8, "comment ");
    } else if (w[0] == "format") {
      const size_t point = w.size() == 3 ? w[2].find('.') : 0;
      if (format || w.size() != 3 ||
          (w[1] != "ascii" && w[1] != "binary_little_endian" && w[1] != "binary_big_endian") ||
          !digits(std::string_view(w[2]).substr(0, point)) ||
          (point != std::string::npos && !digits(std::string_view(w[2]).substr(point + 1)))) {
        fail(fmt::format("line {}: not 'format ascii|binary_little_endian|binary_big_endian VERSION'", number));
      }
      format = true;
    } else if (w[0] == "element") {
      if (w.size() != 3 || !digits(w[2]) || w[2].size() > 10 || std::stoull(w[2]) > 0xFFFFFFFFull) {
        fail(fmt::format("line {}: not 'element NAME COUNT'", number));
      }
      const unsigned long long count = std::stoull(w[2]);
      if (count > body_bytes) {
        fail(fmt::format("line {}: element '{}' has a count ({}) the file's {} data bytes cannot hold", number,
                         w[1], count, body_bytes));
      }
      element = true;
    } else if (w[0] == "property") {
      if (!element) fail(fmt::format("line {}: a property before any element", number));
      if (w.size() == 5 && w[1] == "list") {
        if (!known_type(w[2]) || !known_type(w[3])) {
          fail(fmt::format("line {}: unknown list types '{} {}'", number, w[2], w[3]));
        }
      } else if (w.size() == 3) {
        if (!known_type(w[1])) fail(fmt::format("line {}: unknown property type '{}'", number, w[1]));
      } else {
        fail(fmt::format("line {}: not 'property TYPE NAME' or 'property list TYPE TYPE NAME'", number));
      }
    } else {
      fail(fmt::format("line {}: unexpected '{}'", number, w[0]));
    }
  }
  if (number == 0) fail("empty");
  if (!format) fail("no format line");
  return text;
}

// OpenMesh 9.0's OBJ reader, on two kinds of lines, does what no client's file may make the server do:
// - `mtllib PATH` opens PATH on this machine (relative to the working directory when reading from memory) and
//   reads it whole: `mtllib /dev/zero` allocates until the process dies, a FIFO blocks it for ever, and the
//   materials it loads live in the reader's one shared instance, which concurrent loads would race on. A rig
//   never uses materials, so those lines are blanked before OpenMesh sees them.
// - a face corner without a vertex index (`f /2 3 1`) fails an assertion (abort) or, built without assertions,
//   reads before an empty vector; a corner that is not a number leaves the index uninitialised. Corners are
//   checked first: V, V/VT, V//VN or V/VT/VN, each a decimal integer that fits an int.
// Lines are taken as OpenMesh takes them: split at '\n', trimmed, '#' starts a comment, the first word is the
// keyword. Returns the text to hand to OpenMesh.
// - a `v` line whose numbers do not parse (`v nan 0 0`, `v 1,5 0 0`, `v 1e400 0 0`, `v 1 0`, `v 1.0.0 0 0`) is
//   dropped or half-read by OpenMesh, silently shifting every later index: each is checked here, 3 to 7 finite
//   numbers, and refused naming the line.
// `limits` (vertices, triangles, corners per face, valence) are checked in the same pass.
// (Not tinyobjloader, libtinyobjloader-dev: OpenMesh reads every format here, PLY and STL too; these checks guard
// its OBJ reader rather than add a second parser whose results could differ from it.)
std::string CheckObj(std::string text, const std::string& source, const MeshTextLimits& limits) {
  const auto is_space = [](char c) { return std::isspace(static_cast<unsigned char>(c)) != 0; };
  const auto is_index = [](std::string_view v, bool required) {
    if (v.empty()) return !required;
    if (v[0] == '+' || v[0] == '-') v.remove_prefix(1);
    if (v.empty() || v.size() > 10 || !std::all_of(v.begin(), v.end(), [](char c) { return c >= '0' && c <= '9'; })) {
      return false;
    }
    return std::stoll(std::string(v)) <= std::numeric_limits<int>::max();
  };
  const auto refuse = [&](int line, const std::string& what) {
    throw Error(ErrorCode::kInvalidInput, fmt::format("{}: line {}: {}", source, line, what));
  };
  std::int64_t vertices = 0, triangles = 0;
  std::vector<std::int32_t> valence;  // per vertex seen so far, only with a valence limit
  int number = 0;
  for (size_t at = 0; at < text.size(); ++number) {
    const size_t end = std::min(text.find('\n', at), text.size());
    const std::string_view line(text.data() + at, end - at);
    size_t word = 0;
    while (word < line.size() && is_space(line[word])) ++word;
    size_t word_end = word;
    while (word_end < line.size() && !is_space(line[word_end])) ++word_end;
    const std::string_view keyword = line.substr(word, word_end - word);
    if (keyword == "mtllib") {
      std::fill(text.begin() + static_cast<std::ptrdiff_t>(at), text.begin() + static_cast<std::ptrdiff_t>(end), ' ');
    } else if (keyword == "v") {
      int numbers = 0;
      for (size_t i = word_end; i < line.size();) {
        while (i < line.size() && is_space(line[i])) ++i;
        if (i == line.size() || line[i] == '#') break;
        const size_t start = i;
        while (i < line.size() && !is_space(line[i])) ++i;
        std::string_view item = line.substr(start, i - start);
        if (item.size() > 1 && item[0] == '+') item.remove_prefix(1);
        double value = 0.0;
        const auto [ptr, ec] = std::from_chars(item.data(), item.data() + item.size(), value);
        if (ec != std::errc() || ptr != item.data() + item.size() || !std::isfinite(value)) {
          refuse(number + 1, fmt::format("vertex {}: '{}' is not a finite number", vertices + 1,
                                         line.substr(start, std::min<size_t>(i - start, 32))));
        }
        ++numbers;
      }
      if (numbers < 3 || numbers > 7) {
        refuse(number + 1, fmt::format("vertex {}: 'v' needs x y z (and at most 4 more numbers), got {} numbers",
                                       vertices + 1, numbers));
      }
      if (++vertices > limits.max_vertices && limits.max_vertices > 0) {
        refuse(number + 1, fmt::format("more than {} vertices (the limit)", limits.max_vertices));
      }
      if (limits.max_valence > 0) valence.push_back(0);
    } else if (keyword == "f") {
      std::int64_t corners = 0;
      for (size_t i = word_end; i < line.size();) {
        while (i < line.size() && is_space(line[i])) ++i;
        const size_t start = i;
        while (i < line.size() && !is_space(line[i])) ++i;
        if (i == start) break;
        const std::string_view corner = line.substr(start, i - start);
        const size_t first = corner.find('/');
        const size_t second = first == std::string_view::npos ? first : corner.find('/', first + 1);
        const bool ok =
            is_index(corner.substr(0, first), true) &&
            (first == std::string_view::npos ||
             (is_index(corner.substr(first + 1, second == std::string_view::npos ? second : second - first - 1),
                       false) &&
              (second == std::string_view::npos || is_index(corner.substr(second + 1), false))));
        if (!ok) {
          throw Error(ErrorCode::kInvalidInput,
                      fmt::format("{}: line {}: face corner '{}' is not V, V/VT, V//VN or V/VT/VN (integer "
                                  "indices, V required)",
                                  source, number + 1, corner.substr(0, 32)));
        }
        if (++corners > limits.max_corners_per_face && limits.max_corners_per_face > 0) {
          refuse(number + 1, fmt::format("a face with more than {} corners (the limit)", limits.max_corners_per_face));
        }
        if (limits.max_valence > 0) {
          // OBJ indices are 1-based, negative ones count back from the last vertex.
          const long long index = std::stoll(std::string(corner.substr(0, first)));
          const long long v = index > 0 ? index - 1 : vertices + index;
          if (v >= 0 && v < static_cast<long long>(valence.size()) &&
              ++valence[static_cast<size_t>(v)] > limits.max_valence) {
            refuse(number + 1, fmt::format("vertex {} is in more than {} faces (the valence limit)", v + 1,
                                           limits.max_valence));
          }
        }
      }
      triangles += std::max<std::int64_t>(corners - 2, 0);
      if (limits.max_faces > 0 && triangles > limits.max_faces) {
        refuse(number + 1, fmt::format("more than {} triangles (the limit)", limits.max_faces));
      }
    }
    at = end + 1;
  }
  return text;
}

// Fan-triangulates the polygons as listed (corner 0 with each following pair), then validates.
TriangleMesh Triangulate(const PolygonSoup& soup, const std::string& path) {
  const auto& [points, polygons] = soup;
  TriangleMesh mesh;
  mesh.source = path;
  mesh.name = path;
  mesh.vertices.resize(static_cast<Eigen::Index>(points.size()), 3);
  for (size_t i = 0; i < points.size(); ++i) {
    for (int c = 0; c < 3; ++c) mesh.vertices(static_cast<Eigen::Index>(i), c) = points[i][c];
  }
  size_t triangles = 0;
  for (const auto& polygon : polygons) {
    if (polygon.size() < 3) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("{}: face {} has {} corners", path, &polygon - polygons.data(), polygon.size()));
    }
    triangles += polygon.size() - 2;
  }
  mesh.faces.resize(static_cast<Eigen::Index>(triangles), 3);
  Eigen::Index f = 0;
  for (const auto& polygon : polygons) {
    if (polygon.size() > 3) ++mesh.polygons_split;
    for (size_t k = 1; k + 1 < polygon.size(); ++k, ++f) {
      mesh.faces.row(f) << polygon[0], polygon[k], polygon[k + 1];
    }
  }
  ValidateMesh(mesh);
  return mesh;
}

TriangleMesh ReadWithOpenMesh(std::istream& in, const std::string& format, const std::string& source) {
  PolyMesh scratch;
  RawImporter importer(scratch);
  OpenMesh::IO::Options options;
  if (!OpenMesh::IO::IOManager().read(in, format, importer, options)) {
    throw Error(ErrorCode::kInvalidInput, source + ": OpenMesh could not parse it as ." + format);
  }
  return Triangulate(importer.soup, source);
}

TriangleMesh ReadMesh(std::istream& in, const std::string& format, const std::string& source,
                      const MeshTextLimits& limits = {}) {
  QuietOpenMesh();
  if (format == "stl") return ReadWithOpenMesh(in, format, source);
  // Read whole: OBJ (the server's format) and PLY to check them before OpenMesh, OFF for our own reader.
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (format == "off") return Triangulate(ReadOff(text, source), source);
  text = format == "ply" ? CheckPly(std::move(text), source) : CheckObj(std::move(text), source, limits);
  std::istringstream checked(std::move(text));
  return ReadWithOpenMesh(checked, format, source);
}

}  // namespace

TriangleMesh LoadMesh(const std::string& path) {
  QuietOpenMesh();
  namespace fs = std::filesystem;
  std::error_code ec;
  if (!fs::exists(path, ec)) throw Error(ErrorCode::kNotFound, "mesh file not found: " + path);
  if (!fs::is_regular_file(path, ec)) throw Error(ErrorCode::kInvalidInput, path + ": not a regular file");
  const std::string ext = Lowercase(fs::path(path).extension().string());
  if (ext != ".obj" && ext != ".ply" && ext != ".off" && ext != ".stl") {
    throw Error(ErrorCode::kInvalidInput,
                path + ": unsupported mesh format '" + ext + "' (use .obj, .ply, .off or .stl)");
  }

  std::ifstream in(path, std::ios::binary);
  TriangleMesh mesh = ReadMesh(in, ext.substr(1), path);
  mesh.name = fs::path(path).stem().string();
  return mesh;
}

TriangleMesh LoadMeshFromText(const std::string& text, const std::string& format, const std::string& source,
                              const MeshTextLimits& limits) {
  const std::string f = Lowercase(format);
  if (f != "obj" && f != "ply" && f != "off" && f != "stl") {
    throw Error(ErrorCode::kInvalidInput, source + ": unsupported mesh format '" + format + "'");
  }
  std::istringstream in(text);
  return ReadMesh(in, f, source, limits);
}

void ValidateMesh(const TriangleMesh& mesh) {
  const std::string& src = mesh.source.empty() ? mesh.name : mesh.source;
  if (mesh.vertices.rows() == 0) throw Error(ErrorCode::kInvalidInput, src + ": the mesh has no vertices");
  if (mesh.faces.rows() == 0) throw Error(ErrorCode::kInvalidInput, src + ": the mesh has no faces");
  for (Eigen::Index v = 0; v < mesh.vertices.rows(); ++v) {
    for (int c = 0; c < 3; ++c) {
      if (!std::isfinite(mesh.vertices(v, c))) {
        throw Error(ErrorCode::kInvalidInput,
                    fmt::format("{}: vertex {} has a non-finite {} coordinate ({})", src, v,
                                "xyz"[c], mesh.vertices(v, c)));
      }
    }
  }
  const Eigen::Index n = mesh.vertices.rows();
  for (Eigen::Index f = 0; f < mesh.faces.rows(); ++f) {
    for (int c = 0; c < 3; ++c) {
      const int v = mesh.faces(f, c);
      if (v < 0 || v >= n) {
        throw Error(ErrorCode::kInvalidInput,
                    fmt::format("{}: face {} refers to vertex {}, but the mesh has {} vertices", src,
                                f, v, n));
      }
    }
    if (mesh.faces(f, 0) == mesh.faces(f, 1) || mesh.faces(f, 1) == mesh.faces(f, 2) ||
        mesh.faces(f, 0) == mesh.faces(f, 2)) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("{}: face {} repeats a vertex ({} {} {})", src, f, mesh.faces(f, 0),
                              mesh.faces(f, 1), mesh.faces(f, 2)));
    }
  }
}

void WriteObj(const std::string& path, const Points& vertices, const Faces& faces) {
  try {
    auto out = fmt::output_file(path);
    for (Eigen::Index v = 0; v < vertices.rows(); ++v) {
      out.print("v {} {} {}\n", vertices(v, 0), vertices(v, 1), vertices(v, 2));
    }
    for (Eigen::Index f = 0; f < faces.rows(); ++f) {
      out.print("f {} {} {}\n", faces(f, 0) + 1, faces(f, 1) + 1, faces(f, 2) + 1);
    }
    out.close();
  } catch (const std::system_error& e) {
    throw Error(ErrorCode::kInvalidInput, "cannot write " + path + ": " + e.what());
  }
}

double BoundingBoxDiagonal(const Points& vertices) {
  if (vertices.rows() == 0) return 0.0;
  return (vertices.colwise().maxCoeff() - vertices.colwise().minCoeff()).norm();
}

}  // namespace springblend
