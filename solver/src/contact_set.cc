#include "contact_set.h"

namespace springblend::internal {

bool ContactSet::Update(const std::vector<Collider>& colliders, const std::vector<RigidTransform>& motions,
                        const Eigen::VectorXd& reaction, int surface_vertices, double offset,
                        double release_force, const std::vector<char>& base_held, Eigen::VectorXd* x,
                        std::vector<char>* held) {
  bool changed = false;
  std::vector<char>& fixed = *held;
  std::vector<Contact> kept;
  for (const Contact& c : contacts_) {
    if (reaction.segment<3>(3 * c.vertex).dot(c.normal) > release_force) {
      for (int k = 0; k < 3; ++k) fixed[3 * c.vertex + k] = base_held[3 * c.vertex + k];
      changed = true;
    } else {
      kept.push_back(c);
    }
  }
  contacts_ = std::move(kept);
  // Interior and cap vertices never become contacts (paper section 4).
  for (int v = 0; v < surface_vertices; ++v) {
    if (fixed[3 * v] && fixed[3 * v + 1] && fixed[3 * v + 2]) continue;
    for (size_t i = 0; i < colliders.size(); ++i) {
      Eigen::Vector3d surface, normal;
      if (!colliders[i].Penetrates(x->segment<3>(3 * v), motions[i], &surface, &normal)) continue;
      x->segment<3>(3 * v) = surface + offset * normal;
      fixed[3 * v] = fixed[3 * v + 1] = fixed[3 * v + 2] = 1;
      contacts_.push_back({v, normal});
      changed = true;
      break;
    }
  }
  return changed;
}

}  // namespace springblend::internal
