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
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <mutex>
#include <sstream>
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

// OpenMesh 9.0's PLY reader trusts its header: a header without end_header loops forever and garbled ones
// crash it. The header is checked here first, strictly, so a bad file gets an error naming the line and never
// reaches that reader. (Its OFF reader trusted the counts as well; OFF has a reader of its own, off_reader.cc.)
void CheckPlyHeader(const std::string& text, const std::string& source) {
  constexpr size_t kMaxHeader = 1 << 16;
  const auto fail = [&](const std::string& what) {
    throw Error(ErrorCode::kInvalidInput, fmt::format("{}: PLY header: {}", source, what));
  };
  const size_t end = text.find("end_header");
  if (end == std::string::npos || end > kMaxHeader) fail("no end_header line in the first 64 KiB");
  const size_t body = text.find('\n', end);
  const size_t body_bytes = body == std::string::npos ? 0 : text.size() - body - 1;
  std::istringstream header(text.substr(0, end));
  std::string line;
  int number = 0;
  bool format = false;
  bool element = false;
  static const std::vector<std::string> kTypes = {"char",  "uchar", "short",  "ushort",  "int",    "uint",
                                                  "float", "double", "int8",  "uint8",   "int16",  "uint16",
                                                  "int32", "uint32", "float32", "float64"};
  const auto known_type = [&](const std::string& t) {
    return std::find(kTypes.begin(), kTypes.end(), t) != kTypes.end();
  };
  const auto is_count = [](const std::string& t) {
    return !t.empty() && t.size() <= 12 && std::all_of(t.begin(), t.end(), [](unsigned char c) { return std::isdigit(c); });
  };
  while (std::getline(header, line)) {
    ++number;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    std::istringstream split(line);
    std::vector<std::string> w;
    for (std::string word; split >> word;) w.push_back(word);
    if (number == 1) {
      if (w.size() != 1 || w[0] != "ply") fail("the first line is not 'ply'");
      continue;
    }
    if (w.empty() || w[0] == "comment" || w[0] == "obj_info") continue;
    if (w[0] == "format") {
      if (w.size() != 3 || (w[1] != "ascii" && w[1] != "binary_little_endian" && w[1] != "binary_big_endian")) {
        fail(fmt::format("line {}: not 'format ascii|binary_little_endian|binary_big_endian VERSION'", number));
      }
      format = true;
    } else if (w[0] == "element") {
      if (w.size() != 3 || !is_count(w[2])) fail(fmt::format("line {}: not 'element NAME COUNT'", number));
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

TriangleMesh ReadMesh(std::istream& in, const std::string& format, const std::string& source) {
  QuietOpenMesh();
  if (format == "obj" || format == "stl") return ReadWithOpenMesh(in, format, source);
  // Read whole (these are the CLI's formats; the server takes OBJ): PLY to check its header before OpenMesh,
  // OFF for our own reader.
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (format == "off") return Triangulate(ReadOff(text, source), source);
  CheckPlyHeader(text, source);
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

TriangleMesh LoadMeshFromText(const std::string& text, const std::string& format, const std::string& source) {
  const std::string f = Lowercase(format);
  if (f != "obj" && f != "ply" && f != "off" && f != "stl") {
    throw Error(ErrorCode::kInvalidInput, source + ": unsupported mesh format '" + format + "'");
  }
  std::istringstream in(text);
  return ReadMesh(in, f, source);
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
