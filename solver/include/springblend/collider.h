// Rigid obstacles the blended shape interacts with (paper section 4): after each equilibrium, mesh vertices
// inside an obstacle are moved onto its surface and held, and the system is solved again.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <memory>
#include <string>
#include <vector>

#include "springblend/mesh.h"

namespace springblend {

// A rigid motion applied to a collider as given: p -> rotation * p + translation.
struct RigidTransform {
  Eigen::Quaterniond rotation = Eigen::Quaterniond::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
};

namespace internal {
class MeshColliderTree;
}

// Caps on a mesh collider, checked in one linear pass before any CGAL or OpenMesh structure is built: a
// collider's cost (building its half-edge mesh and AABB tree, and every inside test) grows with these, and
// with vertex valence faster than linearly. 0 turns a cap off.
struct MeshColliderLimits {
  int max_vertices = 100'000;
  int max_faces = 200'000;  // triangles, after fan triangulation
  int max_valence = 256;    // faces around one vertex
};

// The geometry of one obstacle, in the coordinates of the rig (before any per-frame motion).
class Collider {
 public:
  enum class Shape { kSphere, kCapsule, kBox, kPlane, kMesh };

  static Collider Sphere(const Eigen::Vector3d& center, double radius);
  // The set of points within `radius` of the segment a-b.
  static Collider Capsule(const Eigen::Vector3d& a, const Eigen::Vector3d& b, double radius);
  // An axis-aligned box (give it a rotation through the frame's transform).
  static Collider Box(const Eigen::Vector3d& center, const Eigen::Vector3d& half_extents);
  // The half-space behind the plane through `point` with outward `normal`.
  static Collider Plane(const Eigen::Vector3d& point, const Eigen::Vector3d& normal);
  // A closed, outward-oriented triangle mesh (an AABB tree answers inside tests and closest points). Refused
  // (Error kInvalidInput naming the problem) before any CGAL call when it is over `limits`, degenerate (a flat
  // or point-like bounding box, a face without area), encloses no volume, or is not a closed edge-manifold
  // surface (every edge used by exactly two faces, in opposite directions). Its inside test is bounded: ray
  // parity along at most a few fixed directions, then the generalized winding number.
  static Collider Mesh(const TriangleMesh& mesh, const MeshColliderLimits& limits = {});

  Shape shape() const { return shape_; }
  const std::string& description() const { return description_; }

  // If p (moved by `motion`'s inverse into this collider's coordinates) lies inside, returns true with the
  // closest surface point and the outward normal there, both moved by `motion`.
  bool Penetrates(const Eigen::Vector3d& p, const RigidTransform& motion, Eigen::Vector3d* surface_point,
                  Eigen::Vector3d* normal) const;

 private:
  Collider() = default;
  bool PenetratesAtRest(const Eigen::Vector3d& p, Eigen::Vector3d* surface_point, Eigen::Vector3d* normal) const;

  Shape shape_ = Shape::kSphere;
  std::string description_;
  Eigen::Vector3d a_ = Eigen::Vector3d::Zero();  // center, segment start, box center or plane point
  Eigen::Vector3d b_ = Eigen::Vector3d::Zero();  // segment end, box half extents or plane normal
  double radius_ = 0.0;
  std::shared_ptr<const internal::MeshColliderTree> tree_;
};

}  // namespace springblend
