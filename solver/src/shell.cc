// Thickness for surfaces that get no interior (RigOptions::shell): an inner layer offset against each
// shape's own vertex normals, joined to the surface by a prism of springs.
#include <fmt/format.h>

#include "rig_builder.h"

namespace springblend {

using internal::PairKey;

namespace {

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

}  // namespace

void RigBuilder::BuildShell() {
  Rig& rig = r_;
  internal::Interior& interior = interior_;

  RigSummary& s = rig.summary_;
  const Points& rest = rig.rest_.vertices;
  const int n = static_cast<int>(rest.rows());
  double edge_sum = 0.0;
  int edges = 0;
  Eigen::VectorXd incident_sum = Eigen::VectorXd::Zero(n);
  Eigen::VectorXi incident = Eigen::VectorXi::Zero(n);
  for (size_t q = 0; q < rig.spring_a_.size(); ++q) {
    if (rig.spring_kind_[q] != SpringKind::kStructure) continue;
    const int a = rig.spring_a_[q], b = rig.spring_b_[q];
    const double length = (rest.row(a) - rest.row(b)).norm();
    edge_sum += length;
    ++edges;
    incident_sum[a] += length, incident_sum[b] += length;
    ++incident[a], ++incident[b];
  }
  shell_offset_ = rig.options_.shell_thickness * (edges > 0 ? edge_sum / edges : 0.0);
  // Each vertex's inner copy sits as deep as its own edges are long (at most the mean): where the mesh is fine
  // (a mouth corner's crease) a uniform depth would fold the layer over itself.
  shell_offsets_.resize(n);
  for (int v = 0; v < n; ++v) {
    const double local = incident[v] > 0 ? rig.options_.shell_thickness * incident_sum[v] / incident[v] : shell_offset_;
    shell_offsets_[v] = std::min(shell_offset_, local);
  }
  shell_normals_rest_ = VertexNormals(rest, rig.rest_.faces, nullptr);
  interior.vertices.resize(2 * n, 3);
  interior.vertices.topRows(n) = rest;
  interior.vertices.bottomRows(n) = rest - shell_offsets_.asDiagonal() * shell_normals_rest_;
  // The layer resists bending by itself; the bending springs would only widen the Hessian's bandwidth
  // (distance-2 neighbours), which costs 1.7 times the factor's fill on the face. Drop them.
  size_t kept = 0;
  for (size_t q = 0; q < rig.spring_a_.size(); ++q) {
    if (rig.spring_kind_[q] == SpringKind::kBending) {
      springs_.erase(PairKey(rig.spring_a_[q], rig.spring_b_[q]));
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
  for (int v = 0; v < n; ++v) AddSpring(PairKey(v, n + v), SpringKind::kInternal);
  for (size_t q = 0; q < structure; ++q) {
    if (rig.spring_kind_[q] != SpringKind::kStructure) continue;
    const int a = rig.spring_a_[q], b = rig.spring_b_[q];
    AddSpring(PairKey(n + a, n + b), SpringKind::kInternal);
    AddSpring(PairKey(a, n + b), SpringKind::kInternal);
    AddSpring(PairKey(b, n + a), SpringKind::kInternal);
  }
  s.shell_vertices = n;
  s.interior = "shell";
  s.interior_reason = fmt::format("{}; thickness from an inner layer {:.3g} ({} mean edge length) inside",
                                  s.interior_reason, shell_offset_, rig.options_.shell_thickness);
}

void RigBuilder::PlaceShell() {
  Rig& rig = r_;

  // Each target's inner layer: offset against that target's own vertex normals, so every target is an
  // unstressed state of the whole system.
  const int n = rig.summary_.surface_vertices;
  for (size_t t = 0; t < rig.targets_.size(); ++t) {
    const Points& x = rig.targets_[t].vertices;
    const Points normals = VertexNormals(x, rig.rest_.faces, &shell_normals_rest_);
    Points& shape = rig.shapes_[t + 1];
    shape.topRows(n) = x;
    shape.bottomRows(n) = x - shell_offsets_.asDiagonal() * normals;
  }
}

}  // namespace springblend
