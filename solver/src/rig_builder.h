// Building a rig, step by step (paper sections 3.1 and 3.4): springs, the volume or a shell, boundary
// detection, the Hessian's pattern and analysis, then each target's interior placed by a solve with its
// surface held. rig.cc orchestrates; each step lives in its own file.
#pragma once

#include <cstdint>
#include <memory>
#include <unordered_set>
#include <vector>

#include "interior.h"
#include "rig_internals.h"
#include "springblend/rig.h"

namespace springblend {

class RigBuilder {
 public:
  static std::shared_ptr<const Rig> Build(TriangleMesh rest, std::vector<TargetSpec> targets,
                                          const RigOptions& options, const RigBuildControl& control);

 private:
  explicit RigBuilder(std::shared_ptr<Rig> rig) : rig_(std::move(rig)), r_(*rig_) {}

  // springs.cc
  static void CheckTargets(const TriangleMesh& rest, const std::vector<TriangleMesh>& targets);
  void AddSpring(std::uint64_t key, SpringKind kind);
  void BuildSurfaceSprings();
  void BuildInterior();
  void BuildIncidence();
  void ComputeRestLengths();
  void FindDegenerateFaces();
  // shell.cc
  void BuildShell();
  void PlaceShell();
  // shape_controls.cc
  // Checks the specs and turns them into the sculpted shapes (targets_), the names and the controls.
  void ExpandSpecs(std::vector<TargetSpec> specs);
  // Scales each masked shape's offsets (every vertex; interior vertices take their nearest surface vertex's
  // value) and rest-length changes (a spring by the mean of its ends), and refits its anchor motion.
  void ApplyMasks();
  // rig_boundary.cc
  void BuildBoundary();
  // interior_placement.cc
  void PlaceInterior();

  std::shared_ptr<Rig> rig_;
  Rig& r_;
  std::unordered_set<std::uint64_t> springs_;  // vertex pairs that already have a spring
  internal::Interior interior_;
  double shell_offset_ = 0.0;     // the mean edge length times the thickness
  Eigen::VectorXd shell_offsets_;  // per vertex: its inner copy's depth
  Points shell_normals_rest_;
};

namespace internal {

// The key of an unordered vertex pair.
inline std::uint64_t PairKey(int a, int b) {
  if (a > b) std::swap(a, b);
  return (static_cast<std::uint64_t>(static_cast<std::uint32_t>(a)) << 32) | static_cast<std::uint32_t>(b);
}

}  // namespace internal
}  // namespace springblend
