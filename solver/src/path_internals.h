// What the target paths' files (target_paths.cc, path_sweep.cc, path_interpolant.cc, path_serialization.cc)
// share among themselves: the intervals' kinds, the build's cancellation, the samples' tangents, the span step.
#pragma once

#include <Eigen/Core>

#include <cstdint>
#include <optional>
#include <vector>

#include "anchor.h"
#include "spring_system.h"
#include "springblend/error.h"
#include "target_paths.h"

namespace springblend::internal {

// TargetPath::certified's kinds beside 0 and 1: the switch between branches, a fold.
constexpr std::uint8_t kSwitch = 2;
constexpr std::uint8_t kFold = 3;

// A build that was told to stop (TargetPathsOptions::stop, or another target's path was stopped).
[[noreturn]] inline void ThrowCancelled() { throw Error(ErrorCode::kCancelled, "the rig build was cancelled"); }

// Whether sample k has an exact tangent (TargetPath::tangents).
inline bool HasTangent(const TargetPath& path, int k) {
  return static_cast<size_t>(k) < path.tangents.size() && !path.tangents[k].empty();
}

// The span step at alpha on one target's path (path_interpolant.cc), also a midpoint check's first step
// (path_sweep.cc).
int RefineInSpanOf(const TargetPath& path, double alpha, const std::optional<AnchorMotion>& motion,
                   double residual_tolerance, SpringSystem* springs, const std::vector<char>& held,
                   double diagonal_shift, Eigen::VectorXd* x);

}  // namespace springblend::internal
