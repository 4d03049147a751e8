#include "springblend/rig.h"

#include <Eigen/Geometry>

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <numeric>
#include <unordered_map>
#include <unordered_set>

#include "hessian_pattern.h"
#include "sparse_cholesky.h"
#include "anchor.h"
#include "interior.h"
#include "rigid.h"
#include "springblend/solve.h"
#include <tbb/parallel_for.h>

#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>
#include <optional>
#include "springblend/error.h"

namespace springblend {

const char* ToString(ErrorCode code) {
  switch (code) {
    case ErrorCode::kInvalidInput: return "invalid input";
    case ErrorCode::kNotFound: return "not found";
    case ErrorCode::kNumerical: return "numerical failure";
    case ErrorCode::kInternal: return "internal error";
  }
  return "unknown";
}

const char* ToString(SpringKind kind) {
  switch (kind) {
    case SpringKind::kStructure: return "structure";
    case SpringKind::kBending: return "bending";
    case SpringKind::kInternal: return "internal";
  }
  return "unknown";
}

const char* ToString(LinearSolverType type) {
  switch (type) {
    case LinearSolverType::kCholmodSupernodal: return "cholmod";
    case LinearSolverType::kEigenSimplicial: return "eigen";
  }
  return "unknown";
}

LinearSolverType LinearSolverTypeFromString(const std::string& name) {
  if (name == "cholmod") return LinearSolverType::kCholmodSupernodal;
  if (name == "eigen") return LinearSolverType::kEigenSimplicial;
  throw Error(ErrorCode::kInvalidInput, "unknown linear solver '" + name + "' (use cholmod or eigen)");
}

const char* ToString(BoundaryMode mode) {
  switch (mode) {
    case BoundaryMode::kFixedVertices: return "fixed_vertices";
    case BoundaryMode::kPartiallyFixed: return "partially_fixed";
    case BoundaryMode::kFloating: return "floating";
    case BoundaryMode::kAnchored: return "anchored";
  }
  return "unknown";
}

void RigOptions::Validate() const {
  auto in_range = [](double v, double lo, double hi, const char* field) {
    if (!(v >= lo && v <= hi)) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("rig option {} = {} is outside [{}, {}]", field, v, lo, hi));
    }
  };
  if (!std::isfinite(static_tolerance)) {
    throw Error(ErrorCode::kInvalidInput, "rig option static_tolerance must be finite");
  }
  in_range(structure_stiffness, 1e-6, 1e6, "structure_stiffness");
  in_range(bending_stiffness, 0.0, 1e6, "bending_stiffness");
  in_range(internal_stiffness, 0.0, 1e6, "internal_stiffness");
  in_range(min_stiffness_length, 0.0, 1.0, "min_stiffness_length");
  in_range(min_rest_length_fraction, 1e-9, 0.99, "min_rest_length_fraction");
  in_range(radius_edge_ratio, 1.01, 100.0, "radius_edge_ratio");
  in_range(tetgen_timeout_seconds, 0.001, 86400.0, "tetgen_timeout_seconds");
  in_range(anchor_size, 3, 1000, "anchor_size");
  if (!(shell_thickness > 0.0 && shell_thickness <= 100.0)) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("rig option shell_thickness = {} is outside (0, 100]", shell_thickness));
  }
  if (anchor_center && !(std::isfinite((*anchor_center)[0]) && std::isfinite((*anchor_center)[1]) &&
                         std::isfinite((*anchor_center)[2]))) {
    throw Error(ErrorCode::kInvalidInput, "rig option anchor_center must be finite");
  }
}

Rig::~Rig() = default;

std::vector<std::string> Rig::target_names() const {
  std::vector<std::string> names;
  names.reserve(targets_.size());
  for (const auto& t : targets_) names.push_back(t.name);
  return names;
}

class RigBuilder {
 public:
  static std::shared_ptr<const Rig> Build(TriangleMesh rest, std::vector<TriangleMesh> targets,
                                          const RigOptions& options);

 private:
  static void CheckTargets(const TriangleMesh& rest, const std::vector<TriangleMesh>& targets);
  static void BuildSurfaceSprings(Rig& rig, std::unordered_set<std::uint64_t>& springs);
  static void BuildInterior(Rig& rig, std::unordered_set<std::uint64_t>& springs, internal::Interior& interior);
  static void BuildIncidence(Rig& rig);
  static void ComputeRestLengths(Rig& rig);
  static void FindDegenerateFaces(Rig& rig);
  static void BuildBoundary(Rig& rig);
  static void PlaceInterior(const std::shared_ptr<Rig>& rig, const internal::Interior& interior);
  static void BuildShell(Rig& rig, std::unordered_set<std::uint64_t>& springs, internal::Interior& interior);
  static void PlaceShell(Rig& rig);
  static void AddSpring(Rig& rig, std::unordered_set<std::uint64_t>& springs, std::uint64_t key, SpringKind kind);
};

namespace {

std::uint64_t PairKey(int a, int b) {
  if (a > b) std::swap(a, b);
  return (static_cast<std::uint64_t>(static_cast<std::uint32_t>(a)) << 32) |
         static_cast<std::uint32_t>(b);
}

double Elapsed(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
}

// Area-weighted vertex normals of a shape; a vertex whose faces all vanish gets `fallback`'s normal.
Points VertexNormals(const Points& x, const Faces& faces, const Points* fallback) {
  Points normals = Points::Zero(x.rows(), 3);
  for (Eigen::Index f = 0; f < faces.rows(); ++f) {
    const Eigen::RowVector3d e1 = x.row(faces(f, 1)) - x.row(faces(f, 0));
    const Eigen::RowVector3d e2 = x.row(faces(f, 2)) - x.row(faces(f, 0));
    const Eigen::RowVector3d n = e1.cross(e2);  // twice the area, along the normal
    for (int c = 0; c < 3; ++c) normals.row(faces(f, c)) += n;
  }
  for (Eigen::Index v = 0; v < normals.rows(); ++v) {
    const double length = normals.row(v).norm();
    if (length > 0.0) {
      normals.row(v) /= length;
    } else if (fallback != nullptr) {
      normals.row(v) = fallback->row(v);
    }
  }
  return normals;
}

// The vertices of the largest connected set of boundary edges (edges with one face): the outer rim of an
// open surface such as a face mask (the mouth and eye holes are smaller). Empty for a closed surface.
std::vector<int> OuterRim(const Faces& faces, int vertices) {
  std::unordered_map<std::uint64_t, int> count;
  for (Eigen::Index f = 0; f < faces.rows(); ++f) {
    for (int c = 0; c < 3; ++c) ++count[PairKey(faces(f, c), faces(f, (c + 1) % 3))];
  }
  std::vector<int> parent(vertices);
  std::iota(parent.begin(), parent.end(), 0);
  const auto find = [&](int v) {
    while (parent[v] != v) v = parent[v] = parent[parent[v]];
    return v;
  };
  std::vector<char> on_boundary(vertices, 0);
  for (const auto& [key, n] : count) {
    if (n != 1) continue;
    const int a = static_cast<int>(key >> 32), b = static_cast<int>(key & 0xffffffffu);
    on_boundary[a] = on_boundary[b] = 1;
    parent[find(a)] = find(b);
  }
  std::unordered_map<int, int> size;
  for (int v = 0; v < vertices; ++v) {
    if (on_boundary[v]) ++size[find(v)];
  }
  int best = -1;
  for (const auto& [root, n] : size) {
    if (best < 0 || n > size[best] || (n == size[best] && root < best)) best = root;
  }
  std::vector<int> rim;
  for (int v = 0; v < vertices && best >= 0; ++v) {
    if (on_boundary[v] && find(v) == best) rim.push_back(v);
  }
  return rim;
}

}  // namespace

void RigBuilder::CheckTargets(const TriangleMesh& rest, const std::vector<TriangleMesh>& targets) {
  ValidateMesh(rest);
  if (targets.empty()) {
    throw Error(ErrorCode::kInvalidInput,
                "a rig needs at least one target besides the rest shape " + rest.source);
  }
  std::unordered_set<std::string> names;
  for (const auto& t : targets) {
    ValidateMesh(t);
    if (!names.insert(t.name).second) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("{}: the target name '{}' is used twice; target names must be unique",
                              t.source, t.name));
    }
    if (t.vertices.rows() != rest.vertices.rows()) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("{}: target has {} vertices but the rest shape {} has {}", t.source,
                              t.vertices.rows(), rest.source, rest.vertices.rows()));
    }
    if (t.faces.rows() != rest.faces.rows()) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("{}: target has {} faces but the rest shape {} has {}", t.source,
                              t.faces.rows(), rest.source, rest.faces.rows()));
    }
    for (Eigen::Index f = 0; f < rest.faces.rows(); ++f) {
      if (t.faces.row(f) != rest.faces.row(f)) {
        throw Error(ErrorCode::kInvalidInput,
                    fmt::format("{}: face {} is ({} {} {}) but in the rest shape {} it is ({} {} {}); "
                                "every target must have the rest shape's faces",
                                t.source, f, t.faces(f, 0), t.faces(f, 1), t.faces(f, 2), rest.source,
                                rest.faces(f, 0), rest.faces(f, 1), rest.faces(f, 2)));
      }
    }
  }
}

void RigBuilder::AddSpring(Rig& rig, std::unordered_set<std::uint64_t>& springs, std::uint64_t key,
                           SpringKind kind) {
  if (!springs.insert(key).second) return;
  rig.spring_a_.push_back(static_cast<int>(key >> 32));
  rig.spring_b_.push_back(static_cast<int>(key & 0xffffffffu));
  rig.spring_kind_.push_back(kind);
  ++rig.summary_.springs_by_kind[static_cast<int>(kind)];
}

void RigBuilder::BuildSurfaceSprings(Rig& rig, std::unordered_set<std::uint64_t>& springs) {
  const Faces& faces = rig.rest_.faces;
  // Edge -> the corners opposite it, from every face that has it.
  struct EdgeFaces {
    int opposite[2] = {-1, -1};
    int count = 0;
  };
  std::unordered_map<std::uint64_t, EdgeFaces> edges;
  edges.reserve(static_cast<size_t>(faces.rows()) * 2);
  std::vector<std::uint64_t> edge_order;  // first-seen order keeps the spring order deterministic
  edge_order.reserve(static_cast<size_t>(faces.rows()) * 2);
  for (Eigen::Index f = 0; f < faces.rows(); ++f) {
    for (int c = 0; c < 3; ++c) {
      const std::uint64_t key = PairKey(faces(f, c), faces(f, (c + 1) % 3));
      auto [it, inserted] = edges.try_emplace(key);
      if (inserted) edge_order.push_back(key);
      EdgeFaces& e = it->second;
      if (e.count < 2) e.opposite[e.count] = faces(f, (c + 2) % 3);
      ++e.count;
    }
  }
  springs.reserve(edge_order.size() * 3);
  for (std::uint64_t key : edge_order) AddSpring(rig, springs, key, SpringKind::kStructure);
  RigSummary& s = rig.summary_;
  for (std::uint64_t key : edge_order) {
    const EdgeFaces& e = edges[key];
    if (e.count == 1) ++s.boundary_edges;
    if (e.count > 2) ++s.nonmanifold_edges;
    if (rig.options_.bending_springs && e.count == 2 && e.opposite[0] != e.opposite[1]) {
      AddSpring(rig, springs, PairKey(e.opposite[0], e.opposite[1]), SpringKind::kBending);
    }
  }
  if (s.nonmanifold_edges > 0) {
    s.notes.push_back(fmt::format("{} non-manifold edges (more than two faces): no bending spring "
                                  "across them",
                                  s.nonmanifold_edges));
  }
}

void RigBuilder::BuildInterior(Rig& rig, std::unordered_set<std::uint64_t>& springs,
                               internal::Interior& interior) {
  RigSummary& s = rig.summary_;
  if (!rig.options_.interior) {
    s.interior = "surface";
    s.interior_reason = "interior disabled by the rig options: surface springs only";
    interior.vertices = rig.rest_.vertices;
    interior.surface_vertices = s.surface_vertices;
    return;
  }
  internal::TetrahedralizeOptions tet_options;
  tet_options.radius_edge_ratio = rig.options_.radius_edge_ratio;
  tet_options.timeout_seconds = rig.options_.tetgen_timeout_seconds;
  interior = internal::BuildInterior(rig.rest_.vertices, rig.rest_.faces, tet_options);
  s.interior = interior.path == internal::Interior::Path::kClosed   ? "closed"
               : interior.path == internal::Interior::Path::kCapped ? "capped"
                                                                    : "surface";
  s.interior_reason = interior.reason;
  s.cap_vertices = interior.cap_vertices();
  s.interior_vertices = interior.interior_vertices();
  s.tetrahedra = static_cast<int>(interior.tets.rows());
  rig.tets_ = interior.tets;
  for (Eigen::Index t = 0; t < interior.tets.rows(); ++t) {
    for (int i = 0; i < 4; ++i) {
      for (int j = i + 1; j < 4; ++j) {
        AddSpring(rig, springs, PairKey(interior.tets(t, i), interior.tets(t, j)), SpringKind::kInternal);
      }
    }
  }
}

void RigBuilder::BuildIncidence(Rig& rig) {
  const int n = rig.summary_.vertices;
  const int m = static_cast<int>(rig.spring_a_.size());
  rig.summary_.springs = m;
  rig.vertex_spring_offsets_.assign(n + 1, 0);
  for (int q = 0; q < m; ++q) {
    ++rig.vertex_spring_offsets_[rig.spring_a_[q] + 1];
    ++rig.vertex_spring_offsets_[rig.spring_b_[q] + 1];
  }
  for (int v = 0; v < n; ++v) rig.vertex_spring_offsets_[v + 1] += rig.vertex_spring_offsets_[v];
  rig.vertex_springs_.resize(2 * static_cast<size_t>(m));
  std::vector<int> fill(rig.vertex_spring_offsets_.begin(), rig.vertex_spring_offsets_.end() - 1);
  for (int q = 0; q < m; ++q) {
    rig.vertex_springs_[fill[rig.spring_a_[q]]++] = q;
    rig.vertex_springs_[fill[rig.spring_b_[q]]++] = q;
  }
}

void RigBuilder::ComputeRestLengths(Rig& rig) {
  const int m = static_cast<int>(rig.spring_a_.size());
  auto lengths = [&](const Points& x, std::vector<double>& out) {
    out.resize(m);
    for (int q = 0; q < m; ++q) out[q] = (x.row(rig.spring_a_[q]) - x.row(rig.spring_b_[q])).norm();
  };
  lengths(rig.shapes_[0], rig.rest_length0_);
  // The mean over mesh edges: the length scale of the stiffness floor and of tolerances.
  double sum = 0.0;
  int count = 0;
  for (int q = 0; q < m; ++q) {
    if (rig.spring_kind_[q] == SpringKind::kStructure) sum += rig.rest_length0_[q], ++count;
  }
  rig.summary_.mean_rest_length = sum / std::max(count, 1);
  const double unchanged = 1e-12 * rig.summary_.mean_rest_length;
  rig.rest_length_delta_.resize(rig.targets_.size());
  rig.target_changes_lengths_.assign(rig.targets_.size(), 0);
  for (size_t t = 0; t < rig.targets_.size(); ++t) {
    std::vector<double>& d = rig.rest_length_delta_[t];
    lengths(rig.shapes_[t + 1], d);
    for (int q = 0; q < m; ++q) {
      d[q] -= rig.rest_length0_[q];
      if (std::abs(d[q]) > unchanged) rig.target_changes_lengths_[t] = 1;
    }
  }
}

void RigBuilder::FindDegenerateFaces(Rig& rig) {
  const Faces& faces = rig.rest_.faces;
  const double diag = rig.summary_.bounding_box_diagonal;
  const double min_area2 = 1e-24 * diag * diag * diag * diag;  // (1e-12 diag^2)^2
  auto degenerate = [&](const Points& x, Eigen::Index f) {
    const Eigen::RowVector3d e1 = x.row(faces(f, 1)) - x.row(faces(f, 0));
    const Eigen::RowVector3d e2 = x.row(faces(f, 2)) - x.row(faces(f, 0));
    return e1.cross(e2).squaredNorm() <= min_area2;
  };
  RigSummary& s = rig.summary_;
  for (Eigen::Index f = 0; f < faces.rows(); ++f) {
    bool bad = degenerate(rig.rest_.vertices, f);
    for (size_t t = 0; t < rig.targets_.size() && !bad; ++t) bad = degenerate(rig.targets_[t].vertices, f);
    if (bad) {
      if (s.degenerate_faces == 0) s.first_degenerate_face = static_cast<int>(f);
      ++s.degenerate_faces;
    }
  }
  if (s.degenerate_faces > 0) {
    s.notes.push_back(fmt::format("{} degenerate (zero-area) faces in some shape, first face {}; their "
                                  "springs are kept",
                                  s.degenerate_faces, s.first_degenerate_face));
  }
}

void RigBuilder::BuildShell(Rig& rig, std::unordered_set<std::uint64_t>& springs, internal::Interior& interior) {
  RigSummary& s = rig.summary_;
  const Points& rest = rig.rest_.vertices;
  const int n = static_cast<int>(rest.rows());
  double edge_sum = 0.0;
  int edges = 0;
  for (size_t q = 0; q < rig.spring_a_.size(); ++q) {
    if (rig.spring_kind_[q] != SpringKind::kStructure) continue;
    edge_sum += (rest.row(rig.spring_a_[q]) - rest.row(rig.spring_b_[q])).norm();
    ++edges;
  }
  rig.shell_offset_ = rig.options_.shell_thickness * (edges > 0 ? edge_sum / edges : 0.0);
  rig.shell_normals_rest_ = VertexNormals(rest, rig.rest_.faces, nullptr);
  interior.vertices.resize(2 * n, 3);
  interior.vertices.topRows(n) = rest;
  interior.vertices.bottomRows(n) = rest - rig.shell_offset_ * rig.shell_normals_rest_;
  // The layer resists bending by itself; the bending springs would only widen the Hessian's bandwidth
  // (distance-2 neighbours), which costs 1.7 times the factor's fill on the face. Drop them.
  size_t kept = 0;
  for (size_t q = 0; q < rig.spring_a_.size(); ++q) {
    if (rig.spring_kind_[q] == SpringKind::kBending) {
      springs.erase(PairKey(rig.spring_a_[q], rig.spring_b_[q]));
      continue;
    }
    rig.spring_a_[kept] = rig.spring_a_[q];
    rig.spring_b_[kept] = rig.spring_b_[q];
    rig.spring_kind_[kept] = rig.spring_kind_[q];
    ++kept;
  }
  rig.spring_a_.resize(kept);
  rig.spring_b_.resize(kept);
  rig.spring_kind_.resize(kept);
  s.springs_by_kind[static_cast<int>(SpringKind::kBending)] = 0;
  // Springs of the prism layer: each vertex to its inner copy, the inner copies of every edge, and both
  // diagonals of the quad between an edge and its inner copy (shear).
  const size_t structure = rig.spring_a_.size();
  for (int v = 0; v < n; ++v) AddSpring(rig, springs, PairKey(v, n + v), SpringKind::kInternal);
  for (size_t q = 0; q < structure; ++q) {
    if (rig.spring_kind_[q] != SpringKind::kStructure) continue;
    const int a = rig.spring_a_[q], b = rig.spring_b_[q];
    AddSpring(rig, springs, PairKey(n + a, n + b), SpringKind::kInternal);
    AddSpring(rig, springs, PairKey(a, n + b), SpringKind::kInternal);
    AddSpring(rig, springs, PairKey(b, n + a), SpringKind::kInternal);
  }
  s.shell_vertices = n;
  s.interior = "shell";
  s.interior_reason = fmt::format("{}; thickness from an inner layer {:.3g} ({} mean edge length) inside",
                                  s.interior_reason, rig.shell_offset_, rig.options_.shell_thickness);
}

void RigBuilder::PlaceShell(Rig& rig) {
  // Each target's inner layer: offset against that target's own vertex normals, so every target is an
  // unstressed state of the whole system.
  const int n = rig.summary_.surface_vertices;
  for (size_t t = 0; t < rig.targets_.size(); ++t) {
    const Points& x = rig.targets_[t].vertices;
    const Points normals = VertexNormals(x, rig.rest_.faces, &rig.shell_normals_rest_);
    Points& shape = rig.shapes_[t + 1];
    shape.topRows(n) = x;
    shape.bottomRows(n) = x - rig.shell_offset_ * normals;
  }
}

void RigBuilder::BuildBoundary(Rig& rig) {
  RigSummary& s = rig.summary_;
  const Points& rest = rig.rest_.vertices;
  const int n = static_cast<int>(rest.rows());
  std::vector<char> fixed(n, 0);
  if (rig.options_.static_tolerance >= 0.0) {
    const double tol = rig.options_.static_tolerance * s.bounding_box_diagonal;
    for (int v = 0; v < n; ++v) {
      bool still = true;
      for (size_t t = 0; t < rig.targets_.size() && still; ++t) {
        still = (rig.targets_[t].vertices.row(v) - rest.row(v)).norm() <= tol;
      }
      if (still) {
        fixed[v] = 1;
        ++s.static_vertices;
      }
    }
  }
  for (size_t i = 0; i < rig.options_.fixed_vertices.size(); ++i) {
    const int v = rig.options_.fixed_vertices[i];
    if (v < 0 || v >= n) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("fixed_vertices[{}] = {} is not a vertex of {} (it has {} vertices)", i, v,
                              rig.rest_.source, n));
    }
    if (!fixed[v]) ++s.user_fixed_vertices;
    fixed[v] = 1;
  }
  if (rig.options_.hold_outer_rim && rig.options_.interior && s.interior_vertices == 0 && s.cap_vertices == 0 &&
      s.boundary_edges > 0) {
    // An open sheet with no volume behind it: hold its outer rim on the linear blend, as a face mask is
    // stitched to the head it belongs to. Without it the free rim makes the sheet floppy and its
    // equilibrium ambiguous.
    int held = 0;
    for (int v : OuterRim(rig.rest_.faces, n)) {
      if (!fixed[v]) ++held;
      fixed[v] = 1;
    }
    s.rim_vertices = held;
    s.notes.push_back(fmt::format("open surface without an interior: its outer rim ({} more vertices) is held "
                                  "on the linear blend (RigOptions::hold_outer_rim)",
                                  held));
  }
  for (int v = 0; v < n; ++v) {
    if (fixed[v]) rig.fixed_vertices_.push_back(v);
  }

  // Three points spanning a set: the first, the farthest from it, the farthest from their line.
  auto span = [&](const std::vector<int>& ids, int first) {
    std::array<int, 3> g = {first, -1, -1};
    double best = -1.0;
    for (int v : ids) {
      const double d = (rest.row(v) - rest.row(g[0])).squaredNorm();
      if (d > best) best = d, g[1] = v;
    }
    const Eigen::RowVector3d axis = (rest.row(g[1]) - rest.row(g[0])).normalized();
    best = -1.0;
    for (int v : ids) {
      const Eigen::RowVector3d r = rest.row(v) - rest.row(g[0]);
      const double d = (r - r.dot(axis) * axis).squaredNorm();
      if (d > best) best = d, g[2] = v;
    }
    return std::make_pair(g, std::sqrt(std::max(best, 0.0)));
  };

  const std::vector<int>& ids = rig.fixed_vertices_;
  if (ids.empty()) {
    s.boundary_mode = BoundaryMode::kFloating;
    std::vector<int> all(n);
    std::iota(all.begin(), all.end(), 0);
    const Eigen::RowVector3d centroid = rest.colwise().mean();
    int nearest = 0;
    for (int v = 1; v < n; ++v) {
      if ((rest.row(v) - centroid).squaredNorm() < (rest.row(nearest) - centroid).squaredNorm()) nearest = v;
    }
    auto [gauge, off_line] = span(all, nearest);
    if (off_line <= 1e-9 * s.bounding_box_diagonal) {
      throw Error(ErrorCode::kInvalidInput,
                  rig.rest_.source + ": all vertices are collinear; the rest shape spans no plane");
    }
    rig.gauge_ = gauge;
  } else {
    auto [gauge, off_line] = span(ids, ids.front());
    if (ids.size() >= 3 && off_line > 1e-6 * s.bounding_box_diagonal) {
      s.boundary_mode = BoundaryMode::kFixedVertices;
    } else {
      s.boundary_mode = BoundaryMode::kPartiallyFixed;
      s.notes.push_back(fmt::format(
          "only {} fixed vertices (or all on one line): a rotation about them is free and keeps the "
          "orientation the solve starts from",
          ids.size()));
    }
  }
}

void RigBuilder::PlaceInterior(const std::shared_ptr<Rig>& rig, const internal::Interior& interior) {
  RigSummary& s = rig->summary_;
  const int surface = s.surface_vertices;
  const int pinned = surface + interior.cap_vertices();  // the closed surface TetGen saw
  const int n = s.vertices;
  const int targets = static_cast<int>(rig->targets_.size());
  const Points& rest = rig->shapes_[0];

  // Start guesses: the target's surface and caps; the interior displaced by the harmonic extension of the
  // surface's displacement (uniform weights over the springs), which rarely inverts a tetrahedron where a
  // rigid carry-over of the interior would on large deformations.
  std::optional<Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>> laplacian;
  Eigen::SparseMatrix<double> coupling;  // interior rows, pinned columns
  if (n > pinned) {
    std::vector<Eigen::Triplet<double>> inner, outer;
    for (int q = 0; q < static_cast<int>(rig->spring_a_.size()); ++q) {
      const int ends[2] = {rig->spring_a_[q], rig->spring_b_[q]};
      for (int e = 0; e < 2; ++e) {
        const int i = ends[e], j = ends[1 - e];
        if (i < pinned) continue;
        inner.emplace_back(i - pinned, i - pinned, 1.0);
        if (j >= pinned) {
          inner.emplace_back(i - pinned, j - pinned, -1.0);
        } else {
          outer.emplace_back(i - pinned, j, -1.0);
        }
      }
    }
    Eigen::SparseMatrix<double> l(n - pinned, n - pinned);
    l.setFromTriplets(inner.begin(), inner.end());
    coupling.resize(n - pinned, pinned);
    coupling.setFromTriplets(outer.begin(), outer.end());
    laplacian.emplace(l);
  }
  for (int t = 0; t < targets; ++t) {
    Points x(n, 3);
    const Points& surface_t = rig->targets_[t].vertices;
    x.topRows(surface) = surface_t;
    x.middleRows(surface, interior.cap_vertices()) = internal::CapPositions(interior, surface_t);
    if (n > pinned && laplacian->info() == Eigen::Success) {
      const Eigen::MatrixXd moved = x.topRows(pinned) - rest.topRows(pinned);
      const Eigen::MatrixXd inner_moved = laplacian->solve(-(coupling * moved));
      x.bottomRows(n - pinned) = rest.bottomRows(n - pinned) + inner_moved;
    } else {
      x.bottomRows(n - pinned) = rest.bottomRows(n - pinned);
    }
    rig->shapes_[t + 1] = std::move(x);
  }
  if (n == pinned) return;

  // The anchor: interior vertices near the centre of the volume (or where the user put it). It is the
  // boundary condition of rigs that have none; fixed vertices, where a rig has them, already hold it.
  if (rig->options_.anchor && rig->fixed_vertices_.empty()) {
    Eigen::Vector3d center = Eigen::Vector3d::Zero();
    if (rig->options_.anchor_center) {
      center = Eigen::Vector3d((*rig->options_.anchor_center)[0], (*rig->options_.anchor_center)[1],
                               (*rig->options_.anchor_center)[2]);
    } else {
      double volume = 0.0;
      for (Eigen::Index t = 0; t < rig->tets_.rows(); ++t) {
        const Eigen::Vector3d p0 = rest.row(rig->tets_(t, 0)).transpose();
        const Eigen::Vector3d p1 = rest.row(rig->tets_(t, 1)).transpose();
        const Eigen::Vector3d p2 = rest.row(rig->tets_(t, 2)).transpose();
        const Eigen::Vector3d p3 = rest.row(rig->tets_(t, 3)).transpose();
        const double v = (p1 - p0).dot((p2 - p0).cross(p3 - p0)) / 6.0;
        center += v * (p0 + p1 + p2 + p3) / 4.0;
        volume += v;
      }
      center /= volume;
    }
    std::vector<int> candidates(n - pinned);
    std::iota(candidates.begin(), candidates.end(), pinned);
    rig->anchor_ = internal::ChooseAnchor(rest, candidates, center, rig->options_.anchor_size);
    if (rig->anchor_.empty()) {
      s.notes.push_back("too few interior vertices for an anchor: none used");
    }
  }
  Points anchor_rest(static_cast<Eigen::Index>(rig->anchor_.size()), 3);
  for (size_t i = 0; i < rig->anchor_.size(); ++i) anchor_rest.row(static_cast<Eigen::Index>(i)) = rest.row(rig->anchor_[i]);
  if (!rig->anchor_.empty()) rig->anchor_centroid_ = anchor_rest.colwise().mean().transpose();

  // Each target's interior: fix its closed surface, solve with the rest shape's rest lengths (paper 3.4),
  // make the anchor exactly rigid (Kabsch), and relax the interior once more around it. The rig is complete
  // but for these positions, and a zero weight vector uses the rest shape's lengths only.
  std::shared_ptr<const Rig> view = rig;
  std::vector<Points> placed(targets);
  std::vector<internal::AnchorMotion> motions(targets);
  std::vector<char> converged(targets, 1);
  tbb::parallel_for(0, targets, [&](int t) {
    SolveOptions options;
    options.max_iterations = 300;
    Solver solver(view, options);
    Frame frame{std::vector<double>(targets, 0.0), {}};
    const Points& guess = rig->shapes_[t + 1];
    for (int v = 0; v < pinned; ++v) frame.pins.push_back({v, guess.row(v).transpose()});
    solver.SetWarmStart(guess);
    Points ignored;
    bool ok = solver.Solve(frame, &ignored).converged();
    Points x = solver.all_positions();
    if (!rig->anchor_.empty()) {
      Points anchor_t(anchor_rest.rows(), 3);
      for (size_t i = 0; i < rig->anchor_.size(); ++i) anchor_t.row(static_cast<Eigen::Index>(i)) = x.row(rig->anchor_[i]);
      motions[t] = internal::FitRigidMotion(anchor_rest, anchor_t);
      for (size_t i = 0; i < rig->anchor_.size(); ++i) {
        const Eigen::Vector3d p = motions[t].Apply(anchor_rest.row(static_cast<Eigen::Index>(i)).transpose(),
                                                   rig->anchor_centroid_);
        frame.pins.push_back({rig->anchor_[i], p});
      }
      solver.SetWarmStart(x);
      ok = solver.Solve(frame, &ignored).converged() && ok;
      x = solver.all_positions();
    }
    converged[t] = ok ? 1 : 0;
    placed[t] = std::move(x);
  });
  for (int t = 0; t < targets; ++t) {
    rig->shapes_[t + 1] = std::move(placed[t]);
    if (!converged[t]) {
      ++s.unconverged_placements;
      s.notes.push_back(fmt::format("the interior placement in target '{}' did not converge; its interior "
                                    "is the best found (the target is still reproduced exactly)",
                                    rig->targets_[t].name));
    }
  }
  for (int t = 0; t < targets; ++t) {
    s.inverted_tetrahedra_in_targets += internal::CountInvertedTetrahedra(rig->tets_, rig->shapes_[t + 1]);
  }
  if (s.inverted_tetrahedra_in_targets > 0) {
    s.notes.push_back(fmt::format(
        "{} tetrahedra are inverted in the targets' placed interiors (a spring system does not resist "
        "inversion; the paper's section 5 limit)",
        s.inverted_tetrahedra_in_targets));
  }
  if (!rig->anchor_.empty()) {
    rig->anchor_motions_ = std::move(motions);
    s.anchor_vertices = static_cast<int>(rig->anchor_.size());
    s.boundary_mode = BoundaryMode::kAnchored;
  }
}

std::shared_ptr<const Rig> RigBuilder::Build(TriangleMesh rest, std::vector<TriangleMesh> targets,
                                             const RigOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  options.Validate();
  CheckTargets(rest, targets);

  std::shared_ptr<Rig> rig(new Rig());
  rig->options_ = options;
  rig->rest_ = std::move(rest);
  rig->targets_ = std::move(targets);
  RigSummary& s = rig->summary_;
  s.surface_vertices = static_cast<int>(rig->rest_.vertices.rows());
  s.faces = static_cast<int>(rig->rest_.faces.rows());
  s.targets = static_cast<int>(rig->targets_.size());
  s.polygons_split = rig->rest_.polygons_split;
  s.bounding_box_diagonal = BoundingBoxDiagonal(rig->rest_.vertices);
  if (!(s.bounding_box_diagonal > 0.0)) {
    throw Error(ErrorCode::kInvalidInput, rig->rest_.source + ": all vertices coincide");
  }

  std::unordered_set<std::uint64_t> springs;
  BuildSurfaceSprings(*rig, springs);
  internal::Interior interior;
  BuildInterior(*rig, springs, interior);
  if (options.interior && options.shell && interior.path == internal::Interior::Path::kSurfaceOnly) {
    BuildShell(*rig, springs, interior);
  }
  s.vertices = static_cast<int>(interior.vertices.rows());
  rig->shapes_.assign(rig->targets_.size() + 1, Points());
  rig->shapes_[0] = interior.vertices;
  for (size_t t = 0; t < rig->targets_.size(); ++t) rig->shapes_[t + 1] = rig->shapes_[0];
  BuildIncidence(*rig);
  ComputeRestLengths(*rig);
  FindDegenerateFaces(*rig);
  BuildBoundary(*rig);

  rig->pattern_ = std::make_unique<internal::HessianPattern>(
      internal::HessianPattern::Build(s.vertices, rig->spring_a_, rig->spring_b_));
  s.hessian_nonzeros = static_cast<std::int64_t>(rig->pattern_->matrix.row_indices.size());
  rig->cholesky_ = internal::SparseCholesky::Create(options.linear_solver);
  rig->cholesky_->Analyze(rig->pattern_->matrix);

  if (s.shell_vertices > 0) {
    PlaceShell(*rig);
  } else {
    PlaceInterior(rig, interior);
  }
  ComputeRestLengths(*rig);
  if (s.boundary_mode == BoundaryMode::kFloating) {
    s.notes.push_back(fmt::format(
        "no boundary condition and no anchor: solved in the frame of vertices {}, {}, {} (a 3-2-1 gauge that "
        "adds no force) and rigidly aligned onto the linear blendshape",
        rig->gauge_[0], rig->gauge_[1], rig->gauge_[2]));
  }
  s.precompute_ms = Elapsed(start);
  return rig;
}

std::shared_ptr<const Rig> Rig::Build(TriangleMesh rest, std::vector<TriangleMesh> targets,
                                      const RigOptions& options) {
  return RigBuilder::Build(std::move(rest), std::move(targets), options);
}

}  // namespace springblend
