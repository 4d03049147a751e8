// Each target's interior (paper section 3.4): hold the target's closed surface, solve for the interior
// with the rest shape's rest lengths, fit the anchor's rigid motion and relax once more around it. Drives the
// solver's internal pieces (spring system, linear system, Newton) directly, never the public Solver.
#include <fmt/format.h>
#include <tbb/parallel_for.h>

#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>
#include <numeric>
#include <optional>

#include "minimizer.h"
#include "rig_builder.h"
#include "rigid.h"

namespace springblend {

namespace {

// Minimizes the energy of the rest shape's rest lengths from `start` with the vertices `held` at their start
// positions; returns whether it converged.
bool Relax(const Rig& rig, internal::SpringSystem& springs, internal::LinearSystem& linear,
           internal::Minimizer& newton, const std::vector<int>& held_vertices, Eigen::VectorXd* x) {
  std::vector<char> held(3 * static_cast<size_t>(rig.num_vertices()), 0);
  for (int v : held_vertices) held[3 * v] = held[3 * v + 1] = held[3 * v + 2] = 1;
  internal::MinimizerProblem problem;
  problem.springs = &springs;
  problem.linear = &linear;
  problem.held = &held;
  problem.diagonal = rig.summary().bounding_box_diagonal;
  problem.mean_rest_length = rig.summary().mean_rest_length;
  internal::MinimizerSummary summary;
  internal::MinimizerTiming timing;
  problem.timing = &timing;
  newton.Minimize(problem, x, &summary);
  return summary.termination == internal::MinimizerTermination::kConverged;
}

// Target t's placed vertices, from the guess `start` (its surface and caps exact).
Points PlaceTarget(const Rig& rig, int pinned, const Points& anchor_rest, const Points& start,
                   internal::AnchorMotion* motion, char* converged) {
  const int n = rig.num_vertices();
  internal::SpringSystem springs(internal::TopologyOf(rig));
  springs.set_length_scale(rig.summary().mean_rest_length);
  std::vector<double> rest_lengths;
  internal::BlendRestLengths(rig, std::vector<double>(rig.num_shapes(), 0.0), &rest_lengths);
  springs.SetRestLengths(std::move(rest_lengths), rig.spring_kind(), internal::KindStiffness(rig.options()),
                         internal::StiffnessFloor(rig));
  internal::LinearSystem linear(rig.internals().pattern->matrix, *rig.internals().cholesky,
                                rig.options().linear_solver);
  internal::MinimizerOptions options;
  options.max_iterations = 300;
  const auto newton = internal::Minimizer::Create(options);

  Eigen::VectorXd x(3 * n);
  for (int v = 0; v < n; ++v) x.segment<3>(3 * v) = start.row(v).transpose();
  std::vector<int> held(pinned);
  std::iota(held.begin(), held.end(), 0);
  bool ok = Relax(rig, springs, linear, *newton, held, &x);
  const std::vector<int>& anchor = rig.anchor_vertices();
  if (!anchor.empty()) {
    Points anchor_t(anchor_rest.rows(), 3);
    for (size_t i = 0; i < anchor.size(); ++i) {
      anchor_t.row(static_cast<Eigen::Index>(i)) = x.segment<3>(3 * anchor[i]).transpose();
    }
    *motion = internal::FitRigidMotion(anchor_rest, anchor_t);
    for (size_t i = 0; i < anchor.size(); ++i) {
      x.segment<3>(3 * anchor[i]) =
          motion->Apply(anchor_rest.row(static_cast<Eigen::Index>(i)).transpose(), rig.anchor_centroid());
      held.push_back(anchor[i]);
    }
    ok = Relax(rig, springs, linear, *newton, held, &x) && ok;
  }
  *converged = ok ? 1 : 0;
  Points placed(n, 3);
  for (int v = 0; v < n; ++v) placed.row(v) = x.segment<3>(3 * v).transpose();
  return placed;
}

}  // namespace

void RigBuilder::PlaceInterior() {
  const std::shared_ptr<Rig>& rig = rig_;
  const internal::Interior& interior = interior_;
  RigSummary& s = rig->summary_;
  const int surface = s.surface_vertices;
  const int pinned = surface + interior.cap_vertices();  // the closed surface TetGen saw
  const int n = s.vertices;
  const int targets = static_cast<int>(rig->targets_.size());
  const Points& rest = rig->shapes_[0];

  // Start guesses: the target's surface and caps; the interior displaced by the harmonic extension of the
  // surface's displacement (uniform weights over the springs), which rarely inverts a tetrahedron where a
  // rigid carry-over of the interior would on large deformations.
  std::optional<Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>> laplacian;
  Eigen::SparseMatrix<double> coupling;  // interior rows, pinned columns
  if (n > pinned) {
    std::vector<Eigen::Triplet<double>> inner, outer;
    for (int q = 0; q < static_cast<int>(rig->spring_a_.size()); ++q) {
      const int ends[2] = {rig->spring_a_[q], rig->spring_b_[q]};
      for (int e = 0; e < 2; ++e) {
        const int i = ends[e], j = ends[1 - e];
        if (i < pinned) continue;
        inner.emplace_back(i - pinned, i - pinned, 1.0);
        if (j >= pinned) {
          inner.emplace_back(i - pinned, j - pinned, -1.0);
        } else {
          outer.emplace_back(i - pinned, j, -1.0);
        }
      }
    }
    Eigen::SparseMatrix<double> l(n - pinned, n - pinned);
    l.setFromTriplets(inner.begin(), inner.end());
    coupling.resize(n - pinned, pinned);
    coupling.setFromTriplets(outer.begin(), outer.end());
    laplacian.emplace(l);
  }
  for (int t = 0; t < targets; ++t) {
    Points x(n, 3);
    const Points& surface_t = rig->targets_[t].vertices;
    x.topRows(surface) = surface_t;
    x.middleRows(surface, interior.cap_vertices()) = internal::CapPositions(interior, surface_t);
    if (n > pinned && laplacian->info() == Eigen::Success) {
      const Eigen::MatrixXd moved = x.topRows(pinned) - rest.topRows(pinned);
      const Eigen::MatrixXd inner_moved = laplacian->solve(-(coupling * moved));
      x.bottomRows(n - pinned) = rest.bottomRows(n - pinned) + inner_moved;
    } else {
      x.bottomRows(n - pinned) = rest.bottomRows(n - pinned);
    }
    rig->shapes_[t + 1] = std::move(x);
  }
  if (n == pinned) return;

  // The anchor: interior vertices near the centre of the volume (or where the user put it). It is the
  // boundary condition of rigs that have none; fixed vertices, where a rig has them, already hold it.
  if (rig->options_.anchor && rig->fixed_vertices_.empty()) {
    Eigen::Vector3d center = Eigen::Vector3d::Zero();
    if (rig->options_.anchor_center) {
      center = Eigen::Vector3d((*rig->options_.anchor_center)[0], (*rig->options_.anchor_center)[1],
                               (*rig->options_.anchor_center)[2]);
    } else {
      double volume = 0.0;
      for (Eigen::Index t = 0; t < rig->tets_.rows(); ++t) {
        const Eigen::Vector3d p0 = rest.row(rig->tets_(t, 0)).transpose();
        const Eigen::Vector3d p1 = rest.row(rig->tets_(t, 1)).transpose();
        const Eigen::Vector3d p2 = rest.row(rig->tets_(t, 2)).transpose();
        const Eigen::Vector3d p3 = rest.row(rig->tets_(t, 3)).transpose();
        const double v = (p1 - p0).dot((p2 - p0).cross(p3 - p0)) / 6.0;
        center += v * (p0 + p1 + p2 + p3) / 4.0;
        volume += v;
      }
      center /= volume;
    }
    std::vector<int> candidates(n - pinned);
    std::iota(candidates.begin(), candidates.end(), pinned);
    rig->anchor_ = internal::ChooseAnchor(rest, candidates, center, rig->options_.anchor_size);
    if (rig->anchor_.empty()) {
      s.notes.push_back("too few interior vertices for an anchor: none used");
    }
  }
  Points anchor_rest(static_cast<Eigen::Index>(rig->anchor_.size()), 3);
  for (size_t i = 0; i < rig->anchor_.size(); ++i) anchor_rest.row(static_cast<Eigen::Index>(i)) = rest.row(rig->anchor_[i]);
  if (!rig->anchor_.empty()) rig->anchor_centroid_ = anchor_rest.colwise().mean().transpose();

  // Each target's interior: fix its closed surface, solve with the rest shape's rest lengths (paper 3.4),
  // make the anchor exactly rigid (Kabsch), and relax the interior once more around it. The rig is complete
  // but for these positions, and a zero weight vector uses the rest shape's lengths only.
  std::vector<Points> placed(targets);
  std::vector<internal::AnchorMotion> motions(targets);
  std::vector<char> converged(targets, 1);
  const Rig& view = *rig;
  tbb::parallel_for(0, targets, [&](int t) {
    placed[t] = PlaceTarget(view, pinned, anchor_rest, rig->shapes_[t + 1], &motions[t], &converged[t]);
  });
  for (int t = 0; t < targets; ++t) {
    rig->shapes_[t + 1] = std::move(placed[t]);
    if (!converged[t]) {
      ++s.unconverged_placements;
      s.notes.push_back(fmt::format("the interior placement in target '{}' did not converge; its interior "
                                    "is the best found (the target is still reproduced exactly)",
                                    rig->targets_[t].name));
    }
  }
  for (int t = 0; t < targets; ++t) {
    s.inverted_tetrahedra_in_targets += internal::CountInvertedTetrahedra(rig->tets_, rig->shapes_[t + 1]);
  }
  if (s.inverted_tetrahedra_in_targets > 0) {
    s.notes.push_back(fmt::format(
        "{} tetrahedra are inverted in the targets' placed interiors (a spring system does not resist "
        "inversion; the paper's section 5 limit)",
        s.inverted_tetrahedra_in_targets));
  }
  if (!rig->anchor_.empty()) {
    rig->internals_->anchor_motions = std::move(motions);
    s.anchor_vertices = static_cast<int>(rig->anchor_.size());
    s.boundary_mode = BoundaryMode::kAnchored;
  }
}

}  // namespace springblend
