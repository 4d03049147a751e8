// Boundary conditions found at build time (paper section 3.4): static vertices, the user's fixed ones, an
// open sheet's outer rim, and how the rigid motion is pinned down (or the gauge of a floating rig).
#include <cmath>
#include <fmt/format.h>

#include <numeric>
#include <unordered_map>

#include "boundary_conditions.h"
#include "rig_builder.h"
#include "springblend/error.h"

namespace springblend {

using internal::PairKey;

namespace {

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

void RigBuilder::BuildBoundary() {
  Rig& rig = r_;

  RigSummary& s = rig.summary_;
  const Points& rest = rig.rest_.vertices;
  const int n = static_cast<int>(rest.rows());
  std::vector<char> fixed(n, 0);
  if (rig.options_.static_tolerance >= 0.0) {
    const double tol = rig.options_.static_tolerance * s.bounding_box_diagonal;
    for (int v = 0; v < n; ++v) {
      bool still = true;
      const auto& masks = rig.internals_->controls.masks;
      for (size_t t = 0; t < rig.targets_.size() && still; ++t) {
        const double scale = t < masks.size() && !masks[t].empty() ? std::abs(masks[t][v]) : 1.0;
        still = scale * (rig.targets_[t].vertices.row(v) - rest.row(v)).norm() <= tol;
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
  if (rig.options_.hold_outer_rim && s.boundary_edges > 0) {
    // An open surface (a face mask, with a shell, a capped volume or neither): hold its outer rim on the linear
    // blend, as a mask is stitched to the head it belongs to. The rig is then held whatever its targets move
    // (colliders and pins need that), and a sheet's free rim no longer makes it floppy.
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

  const auto points_of = [&](const std::vector<int>& ids) {
    std::vector<Eigen::Vector3d> points;
    points.reserve(ids.size());
    for (int v : ids) points.emplace_back(rest.row(v).transpose());
    return points;
  };
  const std::vector<int>& ids = rig.fixed_vertices_;
  if (ids.empty()) {
    s.boundary_mode = BoundaryMode::kFloating;
    const Eigen::RowVector3d centroid = rest.colwise().mean();
    int nearest = 0;
    for (int v = 1; v < n; ++v) {
      if ((rest.row(v) - centroid).squaredNorm() < (rest.row(nearest) - centroid).squaredNorm()) nearest = v;
    }
    std::vector<int> all(n);
    std::iota(all.begin(), all.end(), 0);
    const internal::Span span = internal::SpanOf(points_of(all), nearest);
    if (span.off_line <= 1e-9 * s.bounding_box_diagonal) {
      throw Error(ErrorCode::kInvalidInput,
                  rig.rest_.source + ": all vertices are collinear; the rest shape spans no plane");
    }
    rig.gauge_ = span.ids;  // vertex ids, as `all` is the identity
  } else {
    if (internal::SpansRigidly(points_of(ids), s.bounding_box_diagonal)) {
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

}  // namespace springblend
