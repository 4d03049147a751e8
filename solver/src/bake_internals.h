// What the bake (bake.cc) takes from bake_inbetweens.cc: a target's path sampled where it snaps, and its
// in-betweens chosen among the samples and fitted to the path.
#pragma once

#include <cmath>
#include <functional>
#include <vector>

#include "springblend/bake.h"

namespace springblend::internal {

// Largest distance of a vertex between two shapes.
inline double Distance(const Points& a, const Points& b) {
  return std::sqrt((a - b).rowwise().squaredNorm().maxCoeff());
}

// In-betweens chosen among the samples: the knots (interior sample indices, ascending), their shapes and the
// largest error of the piecewise-linear path through them at the samples.
struct Inbetweens {
  std::vector<int> knots;
  std::vector<Points> values;
  double error = 0.0;
  std::vector<double> vertex_errors;  // per vertex, its largest error (of the diagonal), once fitted
};

// err[i][j]: the largest error (of the diagonal) of the straight segment from sample i to sample j at the samples
// between them.
using SegmentErrors = std::vector<std::vector<double>>;
// The chord errors of a path's shapes at its weights `alphas` (ascending).
SegmentErrors ChordErrors(const std::vector<Points>& shapes, const std::vector<double>& alphas, double diagonal);

// A target's in-betweens among its path's samples, as `options` ask (their count or the tolerance, solved or
// fitted shapes). chords: ChordErrors of the shapes.
Inbetweens ChooseInbetweens(const std::vector<Points>& shapes, const std::vector<double>& alphas,
                            const SegmentErrors& chords, const BakeOptions& options, double diagonal);

// Where the path snaps between two samples, frames solved by bisection (`solve`) join its samples. Returns the
// snaps located.
int LocateSnaps(const std::function<void(const std::vector<double>&, std::vector<Points>*)>& solve,
                std::vector<double>* alphas, std::vector<Points>* shapes);

}  // namespace springblend::internal
