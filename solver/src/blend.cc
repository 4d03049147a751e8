// The public helpers of a frame: option and frame validation, the linear blendshape, blended rest
// lengths, sweeps, and the enums' names.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "springblend/error.h"
#include "rig_internals.h"
#include "springblend/solve.h"

namespace springblend {

const char* ToString(HessianMode mode) {
  switch (mode) {
    case HessianMode::kTrueWithProjectedFallback: return "true_with_projected_fallback";
    case HessianMode::kProjected: return "projected";
    case HessianMode::kAbsolute: return "absolute";
  }
  return "unknown";
}

const char* ToString(MinimumCheck check) {
  switch (check) {
    case MinimumCheck::kNotChecked: return "not_checked";
    case MinimumCheck::kMinimum: return "minimum";
    case MinimumCheck::kNotMinimum: return "not_a_minimum";
  }
  return "unknown";
}

const char* ToString(Finish finish) {
  switch (finish) {
    case Finish::kFull: return "full";
    case Finish::kLocal: return "local";
    case Finish::kNone: return "none";
  }
  return "unknown";
}

const char* ToString(Termination termination) {
  switch (termination) {
    case Termination::kConverged: return "converged";
    case Termination::kMaxIterations: return "max_iterations";
    case Termination::kStalled: return "stalled";
    case Termination::kNumericalFailure: return "numerical_failure";
    case Termination::kLinear: return "linear";
    case Termination::kCancelled: return "cancelled";
  }
  return "unknown";
}

const char* ToString(SolveMethod method) {
  switch (method) {
    case SolveMethod::kNewton: return "newton";
    case SolveMethod::kNewtonLaplacian: return "newton-laplacian";
    case SolveMethod::kLbfgs: return "lbfgs";
  }
  return "unknown";
}

const char* ToString(MixModel model) {
  switch (model) {
    case MixModel::kSuperposed: return "superposed";
    case MixModel::kRestLengths: return "rest-lengths";
  }
  return "unknown";
}

MixModel MixModelFromString(const std::string& name) {
  for (MixModel m : {MixModel::kSuperposed, MixModel::kRestLengths}) {
    if (name == ToString(m)) return m;
  }
  throw Error(ErrorCode::kInvalidInput,
              fmt::format("unknown mix model '{}' (use superposed or rest-lengths)", name));
}

SolveMethod SolveMethodFromString(const std::string& name) {
  for (SolveMethod m : {SolveMethod::kNewton, SolveMethod::kNewtonLaplacian, SolveMethod::kLbfgs}) {
    if (name == ToString(m)) return m;
  }
  throw Error(ErrorCode::kInvalidInput,
              fmt::format("unknown solve method '{}' (use newton, newton-laplacian or lbfgs)", name));
}

void SolveOptions::Validate() const {
  auto fail = [](const std::string& what) { throw Error(ErrorCode::kInvalidInput, what); };
  if (!(residual_tolerance > 0.0 && residual_tolerance < 1.0)) {
    fail(fmt::format("solve option residual_tolerance = {} is outside (0, 1)", residual_tolerance));
  }
  if (!(step_tolerance >= 0.0 && step_tolerance < 1.0)) {
    fail(fmt::format("solve option step_tolerance = {} is outside [0, 1)", step_tolerance));
  }
  if (max_iterations < 1 || max_iterations > 10000) {
    fail(fmt::format("solve option max_iterations = {} is outside [1, 10000]", max_iterations));
  }
  if (!(max_step_fraction > 0.0 && max_step_fraction <= 1000.0)) {
    fail(fmt::format("solve option max_step_fraction = {} is outside (0, 1000]", max_step_fraction));
  }
  if (!(local_finish_share > 0.0 && local_finish_share <= 1.0)) {
    fail(fmt::format("solve option local_finish_share = {} is outside (0, 1]", local_finish_share));
  }
  if (max_contact_rounds < 1 || max_contact_rounds > 1000) {
    fail(fmt::format("solve option max_contact_rounds = {} is outside [1, 1000]", max_contact_rounds));
  }
  if (!(contact_offset >= 0.0 && contact_offset <= 0.01)) {
    fail(fmt::format("solve option contact_offset = {} is outside [0, 0.01]", contact_offset));
  }
  if (max_line_search_steps < 1 || max_line_search_steps > 60) {
    fail(fmt::format("solve option max_line_search_steps = {} is outside [1, 60]",
                     max_line_search_steps));
  }
  if (lbfgs_history < 1 || lbfgs_history > 100) {
    fail(fmt::format("solve option lbfgs_history = {} is outside [1, 100]", lbfgs_history));
  }
  if (lbfgs_max_iterations < 1 || lbfgs_max_iterations > 10000) {
    fail(fmt::format("solve option lbfgs_max_iterations = {} is outside [1, 10000]", lbfgs_max_iterations));
  }
  if (max_cg_iterations < 1 || max_cg_iterations > 10000) {
    fail(fmt::format("solve option max_cg_iterations = {} is outside [1, 10000]", max_cg_iterations));
  }
  if (!(refactor_cost_ratio > 0.0 && refactor_cost_ratio <= 100.0)) {
    fail(fmt::format("solve option refactor_cost_ratio = {} is outside (0, 100]", refactor_cost_ratio));
  }
}

void ValidateWeights(const Rig& rig, const std::vector<double>& weights) {
  if (static_cast<int>(weights.size()) != rig.num_targets()) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("weights has {} entries but the rig has {} targets ({})", weights.size(),
                            rig.num_targets(), fmt::join(rig.target_names(), ", ")));
  }
  for (size_t t = 0; t < weights.size(); ++t) {
    if (!std::isfinite(weights[t])) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("weights[{}] (target '{}') is not finite ({})", t, rig.target_names()[t],
                              weights[t]));
    }
    if (std::abs(weights[t]) > kMaxTargetWeight) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("weights[{}] (target '{}') = {} is beyond +-{:g}: the blended shape would overflow", t,
                              rig.target_names()[t], weights[t], kMaxTargetWeight));
    }
  }
  // Shapes past the targets are the in-betweens, then the combinations (Rig::num_shapes).
  const std::vector<double> shape_weights = rig.ShapeWeights(weights);
  const size_t combinations = std::min(rig.combination_names().size(), shape_weights.size());
  const size_t first_combination = shape_weights.size() - combinations;
  for (size_t s = 0; s < shape_weights.size(); ++s) {
    const double w = shape_weights[s];
    if (s >= first_combination) {
      if (!(std::abs(w) <= kMaxTargetWeight)) {
        throw Error(ErrorCode::kInvalidInput,
                    fmt::format("combination '{}' has weight {} (the product of its drivers' weights), beyond "
                                "+-{:g}: the blended shape would overflow",
                                rig.combination_names()[s - first_combination], w, kMaxTargetWeight));
      }
    } else if (!(std::abs(w) <= kMaxShapeWeight)) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("sculpted shape {} ({}) has weight {}, beyond +-{:g}: the blended shape would overflow",
                              s, rig.target(static_cast<int>(s)).name, w, kMaxShapeWeight));
    }
  }
}

void ValidateFrame(const Rig& rig, const Frame& frame, size_t colliders) {
  ValidateWeights(rig, frame.weights);
  const int n = rig.num_vertices();
  for (size_t i = 0; i < frame.pins.size(); ++i) {
    const Pin& pin = frame.pins[i];
    if (pin.vertex < 0 || pin.vertex >= n) {
      throw Error(ErrorCode::kInvalidInput, fmt::format("pins[{}].vertex = {} is not a vertex (the rig has {})",
                                                        i, pin.vertex, n));
    }
    if (!pin.position.allFinite()) {
      throw Error(ErrorCode::kInvalidInput, fmt::format("pins[{}] (vertex {}) has a non-finite position", i, pin.vertex));
    }
  }
  if (!frame.collider_transforms.empty() && frame.collider_transforms.size() != colliders) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("collider_transforms has {} entries but there are {} colliders",
                            frame.collider_transforms.size(), colliders));
  }
  for (size_t i = 0; i < frame.collider_transforms.size(); ++i) {
    const RigidTransform& m = frame.collider_transforms[i];
    if (!m.translation.allFinite() || !m.rotation.coeffs().allFinite() || m.rotation.norm() < 1e-12) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("collider_transforms[{}] is not a finite rigid transform", i));
    }
  }
}

Points LinearBlend(const Rig& rig, const std::vector<double>& weights) {
  ValidateWeights(rig, weights);
  const std::vector<double> shape_weights = rig.ShapeWeights(weights);
  const Points& rest = rig.rest().vertices;
  Points out = rest;
  for (int s = 0; s < rig.num_shapes(); ++s) {
    if (shape_weights[s] != 0.0) out += shape_weights[s] * (rig.target(s).vertices - rest);
  }
  return out;
}

Points LinearBlendAll(const Rig& rig, const std::vector<double>& weights) {
  ValidateWeights(rig, weights);
  return internal::LinearBlendShapes(rig, rig.ShapeWeights(weights));
}

void BlendRestLengths(const Rig& rig, const std::vector<double>& weights, std::vector<double>* blended) {
  ValidateWeights(rig, weights);
  internal::BlendRestLengths(rig, rig.ShapeWeights(weights), blended);
}

namespace internal {

Points LinearBlendShapes(const Rig& rig, const std::vector<double>& shape_weights) {
  const Points& rest = rig.shape(0);
  Points out = rest;
  for (int s = 0; s < rig.num_shapes(); ++s) {
    if (shape_weights[s] != 0.0) out += shape_weights[s] * (rig.shape(s + 1) - rest);
  }
  return out;
}

void BlendRestLengths(const Rig& rig, const std::vector<double>& shape_weights, std::vector<double>* blended) {
  const std::vector<double>& r0 = rig.rest_lengths();
  const int m = rig.num_springs();
  blended->assign(r0.begin(), r0.end());
  double* out = blended->data();
  for (int s = 0; s < rig.num_shapes(); ++s) {
    const double w = shape_weights[s];
    if (w == 0.0 || !rig.target_changes_lengths(s)) continue;
    const double* d = rig.rest_length_delta(s).data();
    for (int q = 0; q < m; ++q) out[q] += w * d[q];
  }
  const double floor = rig.options().min_rest_length_fraction * rig.summary().mean_rest_length;
  for (int q = 0; q < m; ++q) out[q] = std::max(out[q], floor);
}

}  // namespace internal

std::vector<Frame> SweepFrames(const std::vector<double>& end, int steps) {
  if (steps < 1) throw Error(ErrorCode::kInvalidInput, fmt::format("sweep needs at least 1 step, got {}", steps));
  std::vector<Frame> frames(steps);
  for (int i = 0; i < steps; ++i) {
    const double alpha = steps == 1 ? 1.0 : static_cast<double>(i) / (steps - 1);
    frames[i].weights.resize(end.size());
    for (size_t t = 0; t < end.size(); ++t) frames[i].weights[t] = alpha * end[t];
  }
  return frames;
}

}  // namespace springblend
