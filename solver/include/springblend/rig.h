// A rig ("character"): the rest shape G_0 and its blendshape targets G_1..G_m turned into one mass-spring
// system with a rest length per spring and per shape (paper section 3.1). Building a rig is the expensive
// precomputation (springs, boundary conditions, the Hessian's sparsity pattern and its symbolic Cholesky
// analysis); a built rig is immutable and is shared by any number of solvers on any threads.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "springblend/mesh.h"

namespace springblend {

namespace internal {
struct HessianPattern;
class SparseCholesky;
}  // namespace internal

enum class SpringKind : std::uint8_t {
  kStructure = 0,  // a mesh edge
  kBending = 1,    // the two vertices opposite an interior edge (distance-2 neighbours)
};
constexpr int kSpringKindCount = 2;
const char* ToString(SpringKind kind);

enum class LinearSolverType {
  kCholmodSupernodal,  // CHOLMOD supernodal Cholesky on OpenBLAS: the production backend
  kEigenSimplicial,    // Eigen's SimplicialLLT: a slow reference, kept for cross-checks
};
const char* ToString(LinearSolverType type);
LinearSolverType LinearSolverTypeFromString(const std::string& name);  // "cholmod" | "eigen"

struct RigOptions {
  // Vertices whose position differs by at most this fraction of the rest shape's bounding-box diagonal
  // in every target are boundary conditions (paper section 3.4). Negative disables the detection.
  double static_tolerance = 1e-6;
  // Vertices the user fixes (0-based indices into the rest mesh); they move with the linear blend.
  std::vector<int> fixed_vertices;
  // Bending springs across interior edges (paper section 3.1). Without them a surface creases freely.
  bool bending_springs = true;
  // Stiffness k_q = kind_stiffness / max(r̄_q, min_stiffness_length * mean rest length) (paper section 3.5,
  // with a floor so near-zero springs such as touching lips do not dominate the system). Range (0, 1].
  double structure_stiffness = 1.0;
  double bending_stiffness = 1.0;
  double min_stiffness_length = 0.1;
  // Blended rest lengths are clamped from below to this fraction of the spring's rest-shape length, so
  // weights outside [0, 1] never produce a non-positive rest length. Range (0, 1).
  double min_rest_length_fraction = 0.01;
  LinearSolverType linear_solver = LinearSolverType::kCholmodSupernodal;

  // Throws Error(kInvalidInput) naming the field that is out of range.
  void Validate() const;
};

// How the rigid motion of the system is pinned down.
enum class BoundaryMode {
  kFixedVertices,   // at least three non-collinear fixed vertices: the equilibrium is unique
  kPartiallyFixed,  // one or two fixed vertices (or collinear ones): a rotation about them is free; the
                    // solve keeps the start's orientation (a tiny Hessian shift removes the null space)
  kFloating,        // nothing fixed: solved in a canonical frame (3-2-1 gauge on three vertices, which
                    // adds no force), then rigidly aligned (Kabsch) onto the linear blendshape
};
const char* ToString(BoundaryMode mode);

struct RigSummary {
  int surface_vertices = 0;
  int vertices = 0;  // all simulated vertices (surface now; interior and anchor vertices later)
  int faces = 0;
  int targets = 0;
  int springs = 0;
  int springs_by_kind[kSpringKindCount] = {0, 0};
  int static_vertices = 0;  // detected automatically
  int user_fixed_vertices = 0;
  BoundaryMode boundary_mode = BoundaryMode::kFloating;
  int degenerate_faces = 0;  // faces of (near) zero area in any shape; reported, still used
  int first_degenerate_face = -1;
  int boundary_edges = 0;  // edges with one face (open surface)
  int nonmanifold_edges = 0;  // edges with more than two faces (no bending spring across them)
  int polygons_split = 0;
  double bounding_box_diagonal = 0.0;
  double mean_rest_length = 0.0;
  std::int64_t hessian_nonzeros = 0;  // stored entries of the upper triangle
  double precompute_ms = 0.0;
  std::vector<std::string> notes;  // decisions taken while building, in words
};

class Rig {
 public:
  // Validates and builds. Every target must have the rest shape's vertex count and faces. Throws Error
  // naming the file and the vertex or face at fault.
  static std::shared_ptr<const Rig> Build(TriangleMesh rest, std::vector<TriangleMesh> targets,
                                          const RigOptions& options = {});
  ~Rig();
  Rig(const Rig&) = delete;
  Rig& operator=(const Rig&) = delete;

  const RigOptions& options() const { return options_; }
  const RigSummary& summary() const { return summary_; }
  int num_vertices() const { return summary_.vertices; }
  int num_surface_vertices() const { return summary_.surface_vertices; }
  int num_targets() const { return static_cast<int>(targets_.size()); }
  int num_springs() const { return static_cast<int>(spring_a_.size()); }
  const TriangleMesh& rest() const { return rest_; }
  const TriangleMesh& target(int t) const { return targets_[t]; }
  std::vector<std::string> target_names() const;

  // Springs: endpoints a < b, kind, and rest length in the rest shape and per target.
  const std::vector<int>& spring_a() const { return spring_a_; }
  const std::vector<int>& spring_b() const { return spring_b_; }
  const std::vector<SpringKind>& spring_kind() const { return spring_kind_; }
  const std::vector<double>& rest_lengths() const { return rest_length0_; }
  // r_q^t - r_q^0 for target t.
  const std::vector<double>& rest_length_delta(int t) const { return rest_length_delta_[t]; }
  // Whether target t changes any rest length at all (a weight on it can then be skipped).
  bool target_changes_lengths(int t) const { return target_changes_lengths_[t] != 0; }

  // Boundary conditions: sorted vertex indices, moved with the linear blendshape.
  const std::vector<int>& fixed_vertices() const { return fixed_vertices_; }
  BoundaryMode boundary_mode() const { return summary_.boundary_mode; }
  // For kFloating: three vertices spanning the rest shape (origin, axis, plane) used as the gauge.
  const std::array<int, 3>& gauge_vertices() const { return gauge_; }
  // Incident springs of each vertex (CSR): spring ids in [offsets[v], offsets[v+1]).
  const std::vector<int>& vertex_spring_offsets() const { return vertex_spring_offsets_; }
  const std::vector<int>& vertex_springs() const { return vertex_springs_; }

  const internal::HessianPattern& hessian_pattern() const { return *pattern_; }
  // The symbolic factorization, analysed once; solvers clone it and only refactor numerically.
  const internal::SparseCholesky& analyzed_cholesky() const { return *cholesky_; }

 private:
  Rig() = default;
  friend class RigBuilder;

  RigOptions options_;
  RigSummary summary_;
  TriangleMesh rest_;
  std::vector<TriangleMesh> targets_;
  std::vector<int> spring_a_, spring_b_;
  std::vector<SpringKind> spring_kind_;
  std::vector<double> rest_length0_;
  std::vector<std::vector<double>> rest_length_delta_;
  std::vector<char> target_changes_lengths_;
  std::vector<int> fixed_vertices_;
  std::array<int, 3> gauge_ = {-1, -1, -1};
  std::vector<int> vertex_spring_offsets_, vertex_springs_;
  std::unique_ptr<internal::HessianPattern> pattern_;
  std::unique_ptr<internal::SparseCholesky> cholesky_;
};

}  // namespace springblend
