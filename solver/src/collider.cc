#include "springblend/collider.h"

#include <CGAL/AABB_face_graph_triangle_primitive.h>
#include <CGAL/AABB_traits.h>
#include <CGAL/AABB_tree.h>
#include <CGAL/Side_of_triangle_mesh.h>
#include <CGAL/Simple_cartesian.h>
#include <CGAL/Surface_mesh.h>
#include <fmt/format.h>

#include <cmath>
#include <sstream>

#include "springblend/error.h"

namespace springblend {
namespace internal {

// CGAL's AABB tree over a triangle mesh: closest points and a ray-parity inside test.
class MeshColliderTree {
 public:
  using Kernel = CGAL::Simple_cartesian<double>;
  using Point = Kernel::Point_3;
  using SurfaceMesh = CGAL::Surface_mesh<Point>;
  using Primitive = CGAL::AABB_face_graph_triangle_primitive<SurfaceMesh>;
  using Tree = CGAL::AABB_tree<CGAL::AABB_traits<Kernel, Primitive>>;

  explicit MeshColliderTree(const TriangleMesh& mesh) {
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
    tree_.insert(faces(surface_).first, faces(surface_).second, surface_);
    tree_.accelerate_distance_queries();
    inside_ = std::make_unique<CGAL::Side_of_triangle_mesh<SurfaceMesh, Kernel>>(tree_);
  }

  bool Inside(const Eigen::Vector3d& p) const {
    return (*inside_)(Point(p.x(), p.y(), p.z())) == CGAL::ON_BOUNDED_SIDE;
  }
  Eigen::Vector3d Closest(const Eigen::Vector3d& p) const {
    const Point c = tree_.closest_point(Point(p.x(), p.y(), p.z()));
    return {c.x(), c.y(), c.z()};
  }

 private:
  SurfaceMesh surface_;
  Tree tree_;
  std::unique_ptr<CGAL::Side_of_triangle_mesh<SurfaceMesh, Kernel>> inside_;
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
  Collider c;
  c.shape_ = Shape::kPlane;
  c.a_ = point;
  c.b_ = normal.normalized();
  c.description_ = "plane";
  return c;
}

Collider Collider::Mesh(const TriangleMesh& mesh) {
  ValidateMesh(mesh);
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
