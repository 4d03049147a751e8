// Springs (paper section 3.1): mesh edges, bending springs across interior edges, the volume's edges; the
// per-vertex incidence, rest lengths per shape, and degenerate faces.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <unordered_map>

#include "rig_builder.h"
#include "springblend/error.h"

namespace springblend {

using internal::PairKey;

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
                  fmt::format("{}: target '{}' has {} vertices but the rest shape {} has {}", t.source,
                              t.name, t.vertices.rows(), rest.source, rest.vertices.rows()));
    }
    if (t.faces.rows() != rest.faces.rows()) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("{}: target '{}' has {} faces but the rest shape {} has {}", t.source,
                              t.name, t.faces.rows(), rest.source, rest.faces.rows()));
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

void RigBuilder::AddSpring(std::uint64_t key, SpringKind kind) {
  Rig& rig = r_;
  if (!springs_.insert(key).second) return;
  rig.spring_a_.push_back(static_cast<int>(key >> 32));
  rig.spring_b_.push_back(static_cast<int>(key & 0xffffffffu));
  rig.spring_kind_.push_back(kind);
  ++rig.summary_.springs_by_kind[static_cast<int>(kind)];
}

void RigBuilder::BuildSurfaceSprings() {
  Rig& rig = r_;

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
  springs_.reserve(edge_order.size() * 3);
  for (std::uint64_t key : edge_order) AddSpring(key, SpringKind::kStructure);
  RigSummary& s = rig.summary_;
  for (std::uint64_t key : edge_order) {
    const EdgeFaces& e = edges[key];
    if (e.count == 1) ++s.boundary_edges;
    if (e.count > 2) ++s.nonmanifold_edges;
    if (rig.options_.bending_springs && e.count == 2 && e.opposite[0] != e.opposite[1]) {
      AddSpring(PairKey(e.opposite[0], e.opposite[1]), SpringKind::kBending);
    }
  }
  if (s.nonmanifold_edges > 0) {
    s.notes.push_back(fmt::format("{} non-manifold edges (more than two faces): no bending spring "
                                  "across them",
                                  s.nonmanifold_edges));
  }
}

void RigBuilder::BuildInterior() {
  Rig& rig = r_;
  internal::Interior& interior = interior_;

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
        AddSpring(PairKey(interior.tets(t, i), interior.tets(t, j)), SpringKind::kInternal);
      }
    }
  }
}

void RigBuilder::BuildIncidence() {
  Rig& rig = r_;

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

void RigBuilder::ComputeRestLengths() {
  Rig& rig = r_;

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

void RigBuilder::FindDegenerateFaces() {
  Rig& rig = r_;

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

}  // namespace springblend
