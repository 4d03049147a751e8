// The contact active set of one frame (paper section 4): mesh vertices that went inside an obstacle are
// moved to its surface and held there; held ones the springs pull away from it are let go.
#pragma once

#include <Eigen/Core>
#include <vector>

#include "springblend/collider.h"

namespace springblend::internal {

class ContactSet {
 public:
  struct Contact {
    int vertex;
    Eigen::Vector3d normal;  // outward normal of the obstacle where the vertex is held
  };

  void Clear() { contacts_.clear(); }
  // One round: release held contacts whose reaction (spring force on every coordinate) points out of the
  // obstacle by more than `release_force`, then catch surface vertices (ids below `surface_vertices`) inside
  // an obstacle, moving them `offset` outside its surface. Updates *x and *held (a released vertex gets back
  // its `base_held` state). Returns whether the set changed.
  bool Update(const std::vector<Collider>& colliders, const std::vector<RigidTransform>& motions,
              const Eigen::VectorXd& reaction, int surface_vertices, double offset, double release_force,
              const std::vector<char>& base_held, Eigen::VectorXd* x, std::vector<char>* held);
  const std::vector<Contact>& contacts() const { return contacts_; }

 private:
  std::vector<Contact> contacts_;
};

}  // namespace springblend::internal
