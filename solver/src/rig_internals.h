// What a built rig keeps for the solver beyond its public data: the Hessian's pattern and its symbolic
// factorization, and each target's anchor motion. Private to the solver library.
#pragma once

#include <memory>
#include <vector>

#include "anchor.h"
#include "hessian_pattern.h"
#include "sparse_cholesky.h"
#include "spring_system.h"
#include "target_paths.h"
#include "springblend/rig.h"

namespace springblend {

struct Rig::Internals {
  std::unique_ptr<internal::HessianPattern> pattern;
  // The symbolic factorization, analysed once; solvers clone it and only refactor numerically.
  std::unique_ptr<internal::SparseCholesky> cholesky;
  std::vector<internal::AnchorMotion> anchor_motions;  // one per target
  std::vector<internal::TargetPath> paths;  // one per target (RigOptions::target_paths); empty without
};

namespace internal {

// The rig's springs as a topology for a SpringSystem (views into the rig's arrays).
inline SpringTopology TopologyOf(const Rig& rig) {
  SpringTopology topology;
  topology.vertices = rig.num_vertices();
  topology.a = rig.spring_a();
  topology.b = rig.spring_b();
  topology.vertex_spring_offsets = rig.vertex_spring_offsets();
  topology.vertex_springs = rig.vertex_springs();
  topology.pattern = rig.internals().pattern.get();
  return topology;
}

// The stiffness of each kind of spring, k_q = kind / max(r̄_q, floor) (RigOptions).
inline std::array<double, 3> KindStiffness(const RigOptions& options) {
  return {options.structure_stiffness, options.bending_stiffness, options.internal_stiffness};
}
// Blended rest lengths r̄_q = r_q^0 + sum_t w_t (r_q^t - r_q^0), clamped from below; weights unchecked.
void BlendRestLengths(const Rig& rig, const std::vector<double>& weights, std::vector<double>* blended);

inline double StiffnessFloor(const Rig& rig) {
  return rig.options().min_stiffness_length * rig.summary().mean_rest_length;
}

}  // namespace internal
}  // namespace springblend
