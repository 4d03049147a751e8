// The blended mass-spring system of one frame (paper sections 3.2 and 3.5): stiffness from the blended rest
// lengths, energy, forces, per-spring Hessian blocks, their assembly into the fixed pattern, and the
// matrix-free Hessian product. Knows nothing of rigs or frames: the rig builder and the solver both drive it.
#pragma once

#include <Eigen/Core>
#include <array>
#include <span>
#include <vector>

#include "hessian_pattern.h"
#include "springblend/rig.h"

namespace springblend::internal {

// The springs' connectivity, fixed for a character: views into arrays owned by the rig (or its builder).
struct SpringTopology {
  int vertices = 0;
  std::span<const int> a, b;                   // endpoints of spring q, a[q] < b[q]
  std::span<const int> vertex_spring_offsets;  // springs of vertex v: vertex_springs[offsets[v] .. offsets[v+1])
  std::span<const int> vertex_springs;
  const HessianPattern* pattern = nullptr;  // the 3n x 3n Hessian's pattern and slot map
  int springs() const { return static_cast<int>(a.size()); }
};

// How a Hessian block treats a compressed spring, whose transverse stiffness k (1 - r̄/l) is negative.
struct Curvature {
  double negative_scale = 1.0;  // 1: the true Hessian, 0: projected Newton (clamped at zero)
  bool absolute = false;        // use |1 - r̄/l| instead (always positive semi-definite)
};

class SpringSystem {
 public:
  explicit SpringSystem(const SpringTopology& topology);

  // This frame's rest lengths r̄ (one per spring) and the stiffness k_q = kind_stiffness / max(r̄_q, floor).
  void SetRestLengths(std::vector<double> rest_lengths, std::span<const SpringKind> kinds,
                      const std::array<double, 3>& kind_stiffness, double stiffness_floor);
  const std::vector<double>& rest_lengths() const { return rest_length_; }
  const std::vector<double>& stiffness() const { return stiffness_; }

  // E(x) = sum_q k_q (|x_a - x_b| - r̄_q)^2 / 2, x stacked (3n).
  double Energy(const Eigen::VectorXd& x) const;
  // Forces at x (force(): zero on held coordinates; reaction(): every coordinate) and the per-spring
  // Hessian blocks. Returns the largest force on a free coordinate.
  // blocks = false skips the Hessian blocks (a first-order method needs only the forces).
  double Evaluate(const Eigen::VectorXd& x, const std::vector<char>& held, const Curvature& curvature,
                  bool blocks = true);
  // The same, and the Hessian's values in the pattern's layout, with `diagonal_shift` added on the free
  // diagonal and identity rows and columns for held coordinates.
  double Assemble(const Eigen::VectorXd& x, const std::vector<char>& held, const Curvature& curvature,
                  double diagonal_shift, std::vector<double>* values);
  // (H + shift I) v on the free coordinates from the blocks of the last Evaluate or Assemble; held
  // coordinates of the product are zero.
  void HessianProduct(const Eigen::VectorXd& v, const std::vector<char>& held, double shift,
                      Eigen::VectorXd* product);

  // The same for the k columns of v at once (rows are coordinates, row-major so that a vertex's three rows
  // are contiguous): one pass over each vertex's springs. The sums run in a fixed order per vertex.
  using Columns = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
  void HessianProducts(const Columns& v, const std::vector<char>& held, double shift, Columns* product) const;
  const Eigen::VectorXd& force() const { return force_; }
  const Eigen::VectorXd& reaction() const { return reaction_; }
  const SpringTopology& topology() const { return topology_; }
  // A length below which a spring counts as having no direction (scale of the rest lengths).
  void set_length_scale(double mean_rest_length) { tiny_length_ = 1e-12 * mean_rest_length; }

 private:
  double Run(const Eigen::VectorXd& x, const std::vector<char>& held, const Curvature& curvature, double shift,
             std::vector<double>* values, bool blocks);

  SpringTopology topology_;
  double tiny_length_ = 0.0;
  std::vector<double> rest_length_;
  std::vector<double> stiffness_;
  std::vector<double> spring_hessian_;  // per spring: upper triangle of H_q (6)
  std::vector<double> spring_force_;    // per spring: force on endpoint a (3)
  std::vector<double> spring_product_;  // per spring: H_q (v_a - v_b) (3)
  Eigen::VectorXd force_, reaction_;
};

}  // namespace springblend::internal
