#include "springblend/mesh.h"

#include <OpenMesh/Core/IO/IOManager.hh>
#include <OpenMesh/Core/IO/importer/ImporterT.hh>
#include <OpenMesh/Core/Mesh/PolyMesh_ArrayKernelT.hh>
#include <OpenMesh/Core/System/omstream.hh>
#include <fmt/format.h>
#include <fmt/os.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <sstream>

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
    points.push_back({p[0], p[1], p[2]});
    return ImporterT<PolyMesh>::add_vertex(p);
  }
  OpenMesh::VertexHandle add_vertex(const OpenMesh::Vec3d& p) override {
    points.push_back({p[0], p[1], p[2]});
    return ImporterT<PolyMesh>::add_vertex(p);
  }
  // The PLY reader adds a vertex first and sets its position afterwards.
  OpenMesh::VertexHandle add_vertex() override {
    points.push_back({0.0, 0.0, 0.0});
    return ImporterT<PolyMesh>::add_vertex();
  }
  void set_point(OpenMesh::VertexHandle vh, const OpenMesh::Vec3f& p) override {
    if (vh.idx() >= 0 && static_cast<size_t>(vh.idx()) < points.size()) points[vh.idx()] = {p[0], p[1], p[2]};
    ImporterT<PolyMesh>::set_point(vh, p);
  }
  OpenMesh::FaceHandle add_face(const VHandles& indices) override {
    std::vector<int> face;
    face.reserve(indices.size());
    for (const auto& vh : indices) face.push_back(vh.idx());
    polygons.push_back(std::move(face));
    return ImporterT<PolyMesh>::add_face(indices);
  }

  std::vector<std::array<double, 3>> points;
  std::vector<std::vector<int>> polygons;
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

}  // namespace

namespace {
TriangleMesh ReadMesh(std::istream& in, const std::string& format, const std::string& source) {
  QuietOpenMesh();
  PolyMesh scratch;
  RawImporter importer(scratch);
  OpenMesh::IO::Options options;
  if (!OpenMesh::IO::IOManager().read(in, format, importer, options)) {
    throw Error(ErrorCode::kInvalidInput, source + ": OpenMesh could not parse it as ." + format);
  }
  const std::string& path = source;

  TriangleMesh mesh;
  mesh.source = path;
  mesh.name = source;
  mesh.vertices.resize(static_cast<Eigen::Index>(importer.points.size()), 3);
  for (size_t i = 0; i < importer.points.size(); ++i) {
    for (int c = 0; c < 3; ++c) mesh.vertices(static_cast<Eigen::Index>(i), c) = importer.points[i][c];
  }
  size_t triangles = 0;
  for (const auto& polygon : importer.polygons) {
    if (polygon.size() < 3) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("{}: face {} has {} corners", path, &polygon - importer.polygons.data(),
                              polygon.size()));
    }
    triangles += polygon.size() - 2;
  }
  mesh.faces.resize(static_cast<Eigen::Index>(triangles), 3);
  Eigen::Index f = 0;
  for (const auto& polygon : importer.polygons) {
    if (polygon.size() > 3) ++mesh.polygons_split;
    for (size_t k = 1; k + 1 < polygon.size(); ++k, ++f) {
      mesh.faces.row(f) << polygon[0], polygon[k], polygon[k + 1];
    }
  }
  ValidateMesh(mesh);
  return mesh;
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
