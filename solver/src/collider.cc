#include "springblend/collider.h"

#include <CGAL/AABB_face_graph_triangle_primitive.h>
#include <CGAL/AABB_traits.h>
#include <CGAL/AABB_tree.h>
#include <CGAL/Simple_cartesian.h>
#include <CGAL/Surface_mesh.h>
#include <fmt/format.h>

#include <array>
#include <cmath>
#include <cstdint>
#include <unordered_map>
#include <sstream>

#include "springblend/error.h"

namespace springblend {
namespace internal {

// CGAL's AABB tree over a triangle mesh: closest points, and candidate faces for our own bounded inside test.
// (CGAL's Side_of_triangle_mesh retries rays until one misses every edge and vertex; on degenerate input it
// never finds one, so it is not used.)
class MeshColliderTree {
 public:
  using Kernel = CGAL::Simple_cartesian<double>;
  using Point = Kernel::Point_3;
  using SurfaceMesh = CGAL::Surface_mesh<Point>;
  using Primitive = CGAL::AABB_face_graph_triangle_primitive<SurfaceMesh>;
  using Tree = CGAL::AABB_tree<CGAL::AABB_traits<Kernel, Primitive>>;

  explicit MeshColliderTree(const TriangleMesh& mesh) : vertices_(mesh.vertices), faces_(mesh.faces) {
    std::vector<SurfaceMesh::Vertex_index> ids;
    ids.reserve(static_cast<size_t>(mesh.vertices.rows()));
    for (Eigen::Index v = 0; v < mesh.vertices.rows(); ++v) {
      ids.push_back(surface_.add_vertex(Point(mesh.vertices(v, 0), mesh.vertices(v, 1), mesh.vertices(v, 2))));
    }
    for (Eigen::Index f = 0; f < mesh.faces.rows(); ++f) {
      const auto face = surface_.add_face(ids[mesh.faces(f, 0)], ids[mesh.faces(f, 1)], ids[mesh.faces(f, 2)]);
      if (face == SurfaceMesh::null_face()) {
        throw Error(ErrorCode::kInvalidInput,
                    fmt::format("{}: face {} makes the collider non-manifold; a mesh collider must be a "
                                "closed manifold surface",
                                mesh.source, f));
      }
    }
    if (!CGAL::is_closed(surface_)) {
      throw Error(ErrorCode::kInvalidInput,
                  mesh.source + ": a mesh collider must be closed (it has boundary edges), or inside is undefined");
    }
    scale_ = BoundingBoxDiagonal(vertices_);
    tree_.insert(faces(surface_).first, faces(surface_).second, surface_);
    tree_.accelerate_distance_queries();
  }

  // Ray parity along fixed directions: a ray that passes too near an edge or a vertex, or grazes a face, or
  // whose count disagrees with the opposite ray's, is not trusted and the next direction is tried. After
  // kDirections the generalized winding number decides (linear in the faces, so bounded too).
  bool Inside(const Eigen::Vector3d& p) const {
    static const std::array<Eigen::Vector3d, 6> kDirections = {
        Eigen::Vector3d(0.5773502691896258, 0.5773502691896258, 0.5773502691896258),
        Eigen::Vector3d(0.2672612419124244, -0.5345224838248488, 0.8017837257372732).normalized(),
        Eigen::Vector3d(-0.7071067811865475, 0.1414213562373095, 0.6928203230275509).normalized(),
        Eigen::Vector3d(0.1091089451179962, 0.8728715609439696, -0.4753327025131754).normalized(),
        Eigen::Vector3d(-0.3015113445777636, -0.9045340337332909, -0.3015113445777636).normalized(),
        Eigen::Vector3d(0.9341723589627157, -0.2135249963343351, 0.2857142857142857).normalized()};
    std::vector<SurfaceMesh::Face_index> candidates;
    for (const Eigen::Vector3d& d : kDirections) {
      int parity[2] = {0, 0};
      bool trusted = true;
      for (int side = 0; side < 2 && trusted; ++side) {
        const Eigen::Vector3d dir = side == 0 ? d : Eigen::Vector3d(-d);
        candidates.clear();
        tree_.all_intersected_primitives(Kernel::Ray_3(Point(p.x(), p.y(), p.z()), Kernel::Vector_3(dir.x(), dir.y(), dir.z())),
                                         std::back_inserter(candidates));
        for (const auto f : candidates) {
          const Crossing c = Cross(p, dir, static_cast<Eigen::Index>(f.idx()));
          if (c == Crossing::kOnSurface) return false;
          if (c == Crossing::kUnsure) {
            trusted = false;
            break;
          }
          if (c == Crossing::kHit) ++parity[side];
        }
      }
      if (trusted && parity[0] % 2 == parity[1] % 2) return parity[0] % 2 == 1;
    }
    return WindingNumber(p) > 0.5;
  }
  Eigen::Vector3d Closest(const Eigen::Vector3d& p) const {
    const Point c = tree_.closest_point(Point(p.x(), p.y(), p.z()));
    return {c.x(), c.y(), c.z()};
  }

 private:
  enum class Crossing { kMiss, kHit, kUnsure, kOnSurface };

  // Möller-Trumbore with margins: a hit within a relative 1e-9 of an edge, or a ray within 1e-9 of the face's
  // plane, is kUnsure rather than a guess.
  Crossing Cross(const Eigen::Vector3d& p, const Eigen::Vector3d& dir, Eigen::Index f) const {
    constexpr double kMargin = 1e-9;
    const Eigen::Vector3d a = vertices_.row(faces_(f, 0)), b = vertices_.row(faces_(f, 1)), c = vertices_.row(faces_(f, 2));
    const Eigen::Vector3d e1 = b - a, e2 = c - a;
    const Eigen::Vector3d h = dir.cross(e2);
    const double det = e1.dot(h);
    const double size = e1.norm() * e2.norm();
    const Eigen::Vector3d s = p - a;
    const Eigen::Vector3d q = s.cross(e1);
    if (std::abs(det) <= kMargin * size) {
      // Parallel to the plane: the point on the plane (and inside the face) is on the surface, otherwise the
      // ray grazes or misses; grazing is unsure.
      const Eigen::Vector3d n = e1.cross(e2);
      return std::abs(n.normalized().dot(s)) <= kMargin * scale_ ? Crossing::kUnsure : Crossing::kMiss;
    }
    const double u = s.dot(h) / det, v = dir.dot(q) / det, t = e2.dot(q) / det;
    if (u < -kMargin || v < -kMargin || u + v > 1.0 + kMargin) return Crossing::kMiss;
    if (std::abs(t) <= kMargin * scale_) return Crossing::kOnSurface;
    if (t < 0.0) return Crossing::kMiss;
    if (u <= kMargin || v <= kMargin || u + v >= 1.0 - kMargin) return Crossing::kUnsure;
    return Crossing::kHit;
  }

  // The solid angle the surface subtends at p over 4 pi (Van Oosterom and Strackee): 1 inside, 0 outside.
  double WindingNumber(const Eigen::Vector3d& p) const {
    double total = 0.0;
    for (Eigen::Index f = 0; f < faces_.rows(); ++f) {
      const Eigen::Vector3d a = Eigen::Vector3d(vertices_.row(faces_(f, 0))) - p;
      const Eigen::Vector3d b = Eigen::Vector3d(vertices_.row(faces_(f, 1))) - p;
      const Eigen::Vector3d c = Eigen::Vector3d(vertices_.row(faces_(f, 2))) - p;
      const double la = a.norm(), lb = b.norm(), lc = c.norm();
      const double numerator = a.dot(b.cross(c));
      const double denominator = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
      total += 2.0 * std::atan2(numerator, denominator);
    }
    return std::abs(total) / (4.0 * M_PI);
  }

  Points vertices_;
  Faces faces_;
  double scale_ = 1.0;
  SurfaceMesh surface_;
  Tree tree_;
};

}  // namespace internal

namespace {

void Require(bool ok, const std::string& what) {
  if (!ok) throw Error(ErrorCode::kInvalidInput, "collider: " + what);
}

bool Finite(const Eigen::Vector3d& v) { return v.allFinite(); }

// A unit vector along d, or +z when d vanishes (a point exactly at a sphere's centre).
Eigen::Vector3d Direction(const Eigen::Vector3d& d) {
  const double n = d.norm();
  return n > 0.0 ? Eigen::Vector3d(d / n) : Eigen::Vector3d::UnitZ();
}

}  // namespace

Collider Collider::Sphere(const Eigen::Vector3d& center, double radius) {
  Require(Finite(center) && std::isfinite(radius) && radius > 0.0, fmt::format("a sphere needs a finite centre and a radius > 0 (radius {})", radius));
  Collider c;
  c.shape_ = Shape::kSphere;
  c.a_ = center;
  c.radius_ = radius;
  c.description_ = fmt::format("sphere at ({}, {}, {}) radius {}", center.x(), center.y(), center.z(), radius);
  return c;
}

Collider Collider::Capsule(const Eigen::Vector3d& a, const Eigen::Vector3d& b, double radius) {
  Require(Finite(a) && Finite(b) && std::isfinite(radius) && radius > 0.0, fmt::format("a capsule needs finite end points and a radius > 0 (radius {})", radius));
  Collider c;
  c.shape_ = Shape::kCapsule;
  c.a_ = a;
  c.b_ = b;
  c.radius_ = radius;
  c.description_ = fmt::format("capsule radius {}", radius);
  return c;
}

Collider Collider::Box(const Eigen::Vector3d& center, const Eigen::Vector3d& half_extents) {
  Require(Finite(center) && Finite(half_extents) && (half_extents.array() > 0.0).all(),
          fmt::format("a box needs a finite centre and half extents > 0 (got {}, {}, {})", half_extents.x(),
                      half_extents.y(), half_extents.z()));
  Collider c;
  c.shape_ = Shape::kBox;
  c.a_ = center;
  c.b_ = half_extents;
  c.description_ = "box";
  return c;
}

Collider Collider::Plane(const Eigen::Vector3d& point, const Eigen::Vector3d& normal) {
  Require(Finite(point) && Finite(normal) && normal.norm() > 0.0, "a plane needs a finite point and a non-zero normal");
  // A normal whose length overflows (1e200) would normalize to zero and silently disable the plane.
  Require(std::isfinite(normal.norm()),
          fmt::format("the plane's normal ({}, {}, {}) is too long: its length overflows; give a unit normal",
                      normal.x(), normal.y(), normal.z()));
  Collider c;
  c.shape_ = Shape::kPlane;
  c.a_ = point;
  c.b_ = normal.normalized();
  Require(c.b_.allFinite() && std::abs(c.b_.norm() - 1.0) < 1e-6, "the plane's normal cannot be normalized");
  c.description_ = "plane";
  return c;
}

namespace {

// The linear pre-pass of Collider::Mesh: everything that would make CGAL slow, loop or answer nonsense is
// refused here, naming the problem.
void CheckMeshCollider(const TriangleMesh& mesh, const MeshColliderLimits& limits) {
  const std::string& source = mesh.source.empty() ? mesh.name : mesh.source;
  const auto refuse = [&](const std::string& what) {
    throw Error(ErrorCode::kInvalidInput, fmt::format("{}: {}", source, what));
  };
  const Eigen::Index n = mesh.vertices.rows(), m = mesh.faces.rows();
  if (limits.max_vertices > 0 && n > limits.max_vertices) {
    refuse(fmt::format("a mesh collider has {} vertices, over the limit of {}", n, limits.max_vertices));
  }
  if (limits.max_faces > 0 && m > limits.max_faces) {
    refuse(fmt::format("a mesh collider has {} triangles, over the limit of {}", m, limits.max_faces));
  }
  ValidateMesh(mesh);
  if (m < 4) refuse(fmt::format("a closed mesh collider needs at least 4 faces (it has {})", m));
  const Eigen::Vector3d extent = (mesh.vertices.colwise().maxCoeff() - mesh.vertices.colwise().minCoeff()).transpose();
  const double scale = extent.norm();
  if (!std::isfinite(scale)) refuse("the collider's size overflows");
  if (!(extent.minCoeff() > 1e-9 * scale)) {
    refuse(fmt::format("the collider is degenerate: its bounding box is {} x {} x {} (flat, a line or a point)",
                       extent.x(), extent.y(), extent.z()));
  }
  std::vector<int> valence(static_cast<size_t>(n), 0);
  std::unordered_map<std::uint64_t, int> edges;  // directed edge -> uses
  edges.reserve(static_cast<size_t>(3 * m));
  const auto key = [](int a, int b) { return (static_cast<std::uint64_t>(a) << 32) | static_cast<std::uint32_t>(b); };
  double volume = 0.0;
  for (Eigen::Index f = 0; f < m; ++f) {
    const Eigen::Vector3d a = mesh.vertices.row(mesh.faces(f, 0)), b = mesh.vertices.row(mesh.faces(f, 1)),
                          c = mesh.vertices.row(mesh.faces(f, 2));
    const Eigen::Vector3d normal = (b - a).cross(c - a);
    if (!(normal.norm() > 1e-12 * scale * scale)) {
      refuse(fmt::format("face {} has no area (its corners are on one line or at one point)", f));
    }
    volume += a.dot(b.cross(c)) / 6.0;
    for (int k = 0; k < 3; ++k) {
      const int v = mesh.faces(f, k);
      if (limits.max_valence > 0 && ++valence[static_cast<size_t>(v)] > limits.max_valence) {
        refuse(fmt::format("vertex {} is in more than {} faces (the valence limit)", v, limits.max_valence));
      }
      if (++edges[key(v, mesh.faces(f, (k + 1) % 3))] > 1) {
        refuse(fmt::format("face {} uses edge {}-{} in the same direction as another face: the collider is "
                           "non-manifold or inconsistently oriented",
                           f, v, mesh.faces(f, (k + 1) % 3)));
      }
    }
  }
  for (const auto& [edge, uses] : edges) {
    const int a = static_cast<int>(edge >> 32), b = static_cast<int>(edge & 0xffffffffu);
    if (edges.count(key(b, a)) == 0) {
      refuse(fmt::format("edge {}-{} has a face on one side only: a mesh collider must be closed", a, b));
    }
  }
  if (!(std::abs(volume) > 1e-9 * scale * scale * scale)) {
    refuse(fmt::format("the collider encloses no volume ({})", volume));
  }
}

}  // namespace

Collider Collider::Mesh(const TriangleMesh& mesh, const MeshColliderLimits& limits) {
  CheckMeshCollider(mesh, limits);
  Collider c;
  c.shape_ = Shape::kMesh;
  c.tree_ = std::make_shared<internal::MeshColliderTree>(mesh);
  c.description_ = "mesh " + mesh.source;
  return c;
}

bool Collider::PenetratesAtRest(const Eigen::Vector3d& p, Eigen::Vector3d* surface_point,
                                Eigen::Vector3d* normal) const {
  switch (shape_) {
    case Shape::kSphere: {
      if ((p - a_).squaredNorm() >= radius_ * radius_) return false;
      *normal = Direction(p - a_);
      *surface_point = a_ + radius_ * *normal;
      return true;
    }
    case Shape::kCapsule: {
      const Eigen::Vector3d axis = b_ - a_;
      const double length2 = axis.squaredNorm();
      const double s = length2 > 0.0 ? std::clamp((p - a_).dot(axis) / length2, 0.0, 1.0) : 0.0;
      const Eigen::Vector3d closest = a_ + s * axis;
      if ((p - closest).squaredNorm() >= radius_ * radius_) return false;
      *normal = Direction(p - closest);
      *surface_point = closest + radius_ * *normal;
      return true;
    }
    case Shape::kBox: {
      const Eigen::Vector3d local = p - a_;
      const Eigen::Vector3d depth = b_ - local.cwiseAbs();  // distance to each pair of faces
      if ((depth.array() <= 0.0).any()) return false;
      Eigen::Index axis;
      depth.minCoeff(&axis);  // leave through the nearest face
      *normal = Eigen::Vector3d::Zero();
      (*normal)[axis] = local[axis] >= 0.0 ? 1.0 : -1.0;
      *surface_point = p;
      (*surface_point)[axis] = a_[axis] + (*normal)[axis] * b_[axis];
      return true;
    }
    case Shape::kPlane: {
      const double height = (p - a_).dot(b_);
      if (height >= 0.0) return false;
      *normal = b_;
      *surface_point = p - height * b_;
      return true;
    }
    case Shape::kMesh: {
      if (!tree_->Inside(p)) return false;
      *surface_point = tree_->Closest(p);
      *normal = Direction(*surface_point - p);
      return true;
    }
  }
  return false;
}

bool Collider::Penetrates(const Eigen::Vector3d& p, const RigidTransform& motion, Eigen::Vector3d* surface_point,
                          Eigen::Vector3d* normal) const {
  const Eigen::Vector3d at_rest = motion.rotation.conjugate() * (p - motion.translation);
  if (!PenetratesAtRest(at_rest, surface_point, normal)) return false;
  *surface_point = motion.rotation * *surface_point + motion.translation;
  *normal = motion.rotation * *normal;
  return true;
}

}  // namespace springblend
