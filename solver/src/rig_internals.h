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

namespace internal {

// How the targets' weights drive the sculpted shapes (Rig::ShapeWeights).
struct ShapeControls {
  struct Knot {
    double weight;  // in (0, 1]; the last knot of a target is its full shape at 1
    int shape;
  };
  std::vector<std::vector<Knot>> targets;  // per target (frame weight), knots by ascending weight
  struct Combination {
    int shape;                 // the sculpt with every driver at 1
    std::vector<int> drivers;  // targets
  };
  std::vector<Combination> combinations;
  std::vector<std::vector<double>> masks;  // per shape: empty, or one value per surface vertex
};

}  // namespace internal

struct Rig::Internals {
  internal::ShapeControls controls;
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
// Blended rest lengths r̄_q = r_q^0 + sum_s w_s (r_q^s - r_q^0) over the sculpted shapes (Rig::ShapeWeights),
// clamped from below; weights unchecked.
void BlendRestLengths(const Rig& rig, const std::vector<double>& shape_weights, std::vector<double>* blended);
// rest + sum_s w_s (shape_s - rest) of every simulated vertex, per sculpted shape.
Points LinearBlendShapes(const Rig& rig, const std::vector<double>& shape_weights);

inline double StiffnessFloor(const Rig& rig) {
  return rig.options().min_stiffness_length * rig.summary().mean_rest_length;
}

}  // namespace internal
}  // namespace springblend
