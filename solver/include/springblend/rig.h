// A rig ("character"): the rest shape G_0 and its blendshape targets G_1..G_m turned into one mass-spring
// system with a rest length per spring and per shape (paper section 3.1). Building a rig is the expensive
// precomputation (springs, boundary conditions, the Hessian's sparsity pattern and its symbolic Cholesky
// analysis); a built rig is immutable and is shared by any number of solvers on any threads.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "springblend/mesh.h"

namespace springblend {

using Tetrahedra = Eigen::Matrix<int, Eigen::Dynamic, 4, Eigen::RowMajor>;  // #T by 4, 0-based

enum class SpringKind : std::uint8_t {
  kStructure = 0,  // a mesh edge
  kBending = 1,    // the two vertices opposite an interior edge (distance-2 neighbours)
  kInternal = 2,   // an edge of the tetrahedralized volume that is not already a spring
};
constexpr int kSpringKindCount = 3;
const char* ToString(SpringKind kind);

enum class LinearSolverType {
  kCholmodSupernodal,  // CHOLMOD supernodal Cholesky on OpenBLAS, preconditioning with its factor rounded to
                       // single precision (half the memory a solve streams): the production backend
  kCholmodDouble,      // the same, preconditioning with the double factor: the baseline the benchmark compares
  kEigenSimplicial,    // Eigen's SimplicialLLT: a slow reference, kept for cross-checks
  kMumpsSingle,        // MUMPS in single precision, as a step and preconditioner: measured slower here
  kCholmodLibrary,     // kCholmodSupernodal with CHOLMOD's own numeric factorization (one thread) instead of the
                       // tree-parallel one on its analysis: the baseline the benchmark compares
};
const char* ToString(LinearSolverType type);
LinearSolverType LinearSolverTypeFromString(const std::string& name);  // "cholmod" | "cholmod-double" | "cholmod-library" | "eigen" | "mumps"

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
  double internal_stiffness = 1.0;
  double min_stiffness_length = 0.1;
  // Blended rest lengths are clamped from below to this fraction of the spring's rest-shape length, so
  // weights outside [0, 1] never produce a non-positive rest length. Range (0, 1).
  double min_rest_length_fraction = 0.01;
  LinearSolverType linear_solver = LinearSolverType::kCholmodSupernodal;

  // Volume (paper 3.1): tetrahedralize the rest surface with TetGen (open boundaries are capped first) and
  // add the tetrahedra's edges as internal springs. A surface TetGen cannot take falls back to surface
  // springs, and the summary says why.
  bool interior = true;
  double radius_edge_ratio = 2.0;   // TetGen quality bound (-q); > 1, smaller gives more interior points
  double tetgen_timeout_seconds = 120.0;
  // The internal anchor (paper 3.4): `anchor_size` interior vertices near `anchor_center` (default: the
  // centre of the volume) move rigidly with the blended transform and are the boundary condition, so every
  // surface vertex moves freely. Needs the interior.
  bool anchor = true;
  int anchor_size = 8;
  std::optional<std::array<double, 3>> anchor_center;
  // Thickness for surfaces that get no interior (an open sheet such as a face mask, whose caps TetGen
  // refuses, or a self-intersecting closed surface such as the cat): an inner layer of vertices offset against each shape's own vertex normals by
  // shell_thickness times its own mean edge length (at most the mesh's mean: where the mesh is fine, as at a
  // mouth corner's crease, a uniform depth folds the layer over itself and makes the equilibria snap from one
  // weight to the next), joined to the surface by springs along, across and beside every
  // edge (a prism shell). A sheet held only by edge and bending springs is floppy out of its plane (slow,
  // and with several equilibria); the shell makes it resist bending. Each target's layer is placed by its
  // own normals, so targets are still reproduced exactly; the layer replaces the bending springs.
  // Range of the thickness (0, 100].
  bool shell = true;
  double shell_thickness = 1.0;
  // An open surface: also hold the vertices of its outer rim (the largest loop of boundary edges; holes such
  // as a mouth or eyes stay free) on the linear blend, as a face mask is stitched to the head it belongs to.
  // The rig is then held (colliders and pins need that) whatever its targets move. No effect on a closed
  // surface.
  bool hold_outer_rim = false;

  // Stateless frames: solve each target's own path (the target alone at weight alpha, its in-betweens
  // included) for alpha from -path_extension to 1 + path_extension, by continuation from the rest shape (the
  // paper's sweep) at path_intervals steps per unit, one branch per target, and keep the physical corrections.
  // Every frame then starts from the linear blend plus each target's correction at its weight: a
  // single-target frame starts within path_tolerance of its answer and is finished where it is out of balance
  // only, every frame starts close to its answer, and no frame depends on another. Certified: every solved step
  // is kept while path_max_samples allows, else only those the interpolant needs (an interval is split while its
  // interpolant misses a step inside it by more than path_tolerance of the bounding-box diagonal); an interval with no step inside is
  // split until the interpolant at its midpoint is within path_tolerance of an equilibrium solved there; up to
  // path_max_samples per target. A step that jumps to another branch (a fold) breaks the path there. Run in
  // parallel over the targets. Beyond the path's ends a target's correction is that of its end, so a weight
  // outside [-path_extension, 1 + path_extension] starts from it and is solved in full.
  // Range: intervals [1, 256], extension [0, 2], tolerance (0, 0.1], max samples [4, 1024].
  // The defaults make a 55-expression face (6,706 vertices, a shell of 13,412) ready in about 4 minutes on 2
  // cores; 32 steps per unit, 0.25 beyond [0, 1] and 1e-6 took 13 (docs/benchmark.md, Captured takes: the upload).
  bool target_paths = true;
  int path_intervals = 16;
  double path_extension = 0.0;
  double path_tolerance = 1e-5;
  int path_max_samples = 64;

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
  kAnchored,        // the internal anchor moves by the blended rigid transform (plus any fixed vertices)
};
const char* ToString(BoundaryMode mode);

struct RigSummary {
  int surface_vertices = 0;
  int vertices = 0;  // all simulated vertices: surface, cap and interior (anchor vertices are interior)
  int faces = 0;
  int targets = 0;
  int springs = 0;
  int springs_by_kind[kSpringKindCount] = {0, 0, 0};
  int interior_vertices = 0;  // TetGen's Steiner points inside the volume
  int shell_vertices = 0;     // the inner layer of a shell (RigOptions::shell)
  int cap_vertices = 0;       // one per hole closed before tetrahedralizing
  int anchor_vertices = 0;
  int tetrahedra = 0;
  std::string interior;         // "closed", "capped", "shell" or "surface"
  std::string interior_reason;  // why, in words
  int unconverged_placements = 0;  // targets whose interior placement solve did not converge
  int inverted_tetrahedra_in_targets = 0;  // summed over the targets' placed interiors
  int static_vertices = 0;  // detected automatically
  int user_fixed_vertices = 0;
  int rim_vertices = 0;  // held by RigOptions::hold_outer_rim (beyond static and user-fixed ones)
  BoundaryMode boundary_mode = BoundaryMode::kFloating;
  int degenerate_faces = 0;  // faces of (near) zero area in any shape; reported, still used
  int first_degenerate_face = -1;
  int boundary_edges = 0;  // edges with one face (open surface)
  int nonmanifold_edges = 0;  // edges with more than two faces (no bending spring across them)
  int polygons_split = 0;
  double bounding_box_diagonal = 0.0;
  double mean_rest_length = 0.0;
  std::int64_t hessian_nonzeros = 0;  // stored entries of the upper triangle
  int path_samples = 0;              // samples kept along the targets' paths
  int path_solves = 0;               // equilibria solved for them (samples and midpoint checks)
  int unconverged_path_samples = 0;  // samples that did not converge (best found kept)
  int uncertified_path_intervals = 0;  // intervals not certified within the sample cap, and folds
  double path_max_error = 0.0;       // largest certified midpoint error, of the diagonal
  double path_ms = 0.0;              // time spent on the paths (part of precompute_ms)
  bool paths_loaded = false;         // the paths came from RigBuildControl::precomputed, not solved
  std::int64_t path_bytes = 0;       // memory the paths hold
  // Their samples left in RigBuildControl::precomputed_file, read as frames need them (not resident).
  std::int64_t path_file_bytes = 0;
  std::int64_t rig_bytes = 0;        // memory the rig holds without its paths (estimate: arrays it keeps)
  struct TargetPathSummary {
    std::string target;
    int samples = 0;
    int solves = 0;
    int uncertified = 0;
    double max_error = 0.0;  // of the diagonal
    double ms = 0.0;         // wall time of its build (0 when loaded)
    int checks = 0;          // midpoint checks solved (0 when loaded)
    int local_checks = 0;    // of them, finished where the interpolant was out of balance only
    // The target's weights where its path is not certified (a check that did not pass, a fold; neighbouring
    // intervals merged), ascending: a frame there starts farther from its answer and may need a full solve.
    std::vector<std::pair<double, double>> uncertified_ranges;
  };
  std::vector<TargetPathSummary> paths;  // one per target with a path
  double precompute_ms = 0.0;
  std::vector<std::string> notes;  // decisions taken while building, in words
};

// The least distance of an in-between's weight from 0, 1 and the target's other in-betweens: the blend's slope
// between two knots is 1 / their distance (an in-between at 1e-300 gave weights of 1e300).
inline constexpr double kMinInbetweenSpacing = 1e-6;
// The farthest a target, in-between or combination sculpt may take a vertex from the rest shape (times its
// mask), in rest-mesh bounding-box diagonals: Rig::Build refuses farther ones, naming the target and vertex.
inline constexpr double kMaxTargetReach = 10.0;
// Throws Error(kInvalidInput) naming the entry (`field(i)`, e.g. "inbetweens[1].weight") unless every weight is in
// (0, 1) and at least kMinInbetweenSpacing from 0, 1 and the others. Rig::Build checks a target's in-betweens
// with it; a server checks an upload's header with it before the meshes arrive.
void ValidateInbetweenWeights(const std::vector<double>& weights, const std::function<std::string(size_t)>& field);

// A shape reached on the way to a target's full shape (Maya's in-between target).
struct Inbetween {
  double weight = 0.0;  // in (0, 1), kMinInbetweenSpacing from 0, 1 and the target's other in-betweens
  TriangleMesh mesh;
};

// One target of a production rig (a rig file's entry). Weights blend piecewise linearly through the
// in-betweens (each reproduced exactly at its weight); a combination (corrective) is on by the product of its
// drivers' weights, and its mesh, the sculpt with every driver at 1, is reproduced exactly there; a mask
// scales each vertex's offset and each spring's rest-length change (by the mean of its two vertices' values).
struct TargetSpec {
  std::string name;                      // unique among the targets
  TriangleMesh mesh;                     // the shape at weight 1; a combination's with every driver at 1
  std::vector<Inbetween> inbetweens;     // any order; none on a combination
  std::vector<double> mask;              // empty, or one finite weight per rest-mesh vertex; none on a combination
  std::vector<std::string> combination;  // >= 2 distinct names of targets that are not combinations; empty: ordinary
};

// How a rig build goes: what it reports, when it stops, what it may reuse.
struct RigBuildProgress {
  std::string stage;  // "springs", "interior", "analysis", "placement", "paths", "done"
  int targets = 0;              // with a path to build
  int targets_done = 0;
  int samples_done = 0;         // path samples kept by the targets done
  double elapsed_ms = 0.0;
};
// An open file descriptor, closed when the last owner lets it go.
class OpenFile {
 public:
  explicit OpenFile(int fd) : fd_(fd) {}
  ~OpenFile();
  OpenFile(const OpenFile&) = delete;
  OpenFile& operator=(const OpenFile&) = delete;
  int fd() const { return fd_; }

 private:
  int fd_;
};

// Where Rig::SavePrecomputed's bytes are in a file: [offset, offset + size), size -1 for the rest of the file.
struct PrecomputedLocation {
  std::string file;  // for messages, and opened when there is no `opened`
  std::int64_t offset = 0;
  std::int64_t size = -1;
  // The file, already open by whoever checked it: read through (a duplicate of) this descriptor, never by opening
  // `file` again, which something renamed over it since (a FIFO: the open would block for good) would change.
  // Null: `file` is opened without blocking, and must be a regular file.
  std::shared_ptr<const OpenFile> opened;
};

// Tells Rig::SavePrecomputed's bytes, in order, in pieces of a few megabytes to `write`, so they are never held
// together; stops and returns false when `write` returns false. Throws Error(kInternal) naming the file when the
// samples left in a file cannot be read back.
using PrecomputedWriter = std::function<bool(const std::function<bool(std::string_view piece)>& write)>;

struct RigBuildControl {
  // Asked between path samples and Newton iterations; when it says true the build ends with
  // Error(kCancelled). Called on the building threads, possibly concurrently.
  std::function<bool()> stop;
  // Told of each stage and each target's path as it is done (serialized; on a building thread).
  std::function<void(const RigBuildProgress&)> progress;
  // Rig::SavePrecomputed of a rig built from the same meshes and options: its target paths are used rather
  // than solved. Bytes that do not fit this rig (another version, target or vertex count) are not used: the
  // paths are solved and a note says why.
  const std::string* precomputed = nullptr;
  // The same bytes in a file instead (when precomputed is null). The paths' samples then stay in the file, read
  // as frames need them (a few per moved target), so the rig's resident memory does not grow with its expressions
  // (RigSummary::path_bytes, path_file_bytes). The file is opened once (closed and opened again by its name only
  // past SetOpenPathFileLimit, springblend/open_files.h); it must not be changed in place while the
  // rig lives (replace it by renaming, as the server's cache does). A file that cannot be opened or read is
  // treated as bytes that do not fit: the paths are solved and a note says why.
  std::optional<PrecomputedLocation> precomputed_file;
  // A directory where the build leaves each target's path as soon as it is solved, in a file without a name (its
  // disk space given back when the rig that reads it is gone), so a build of many expressions holds the paths
  // being solved rather than all of them. Empty: they are held in memory. A directory where no such file can be
  // made (or a disk that fills) keeps the paths in memory, with a note.
  std::string spool_directory;
  // Called once the paths are solved (not when loaded) with a writer of Rig::SavePrecomputed's bytes, which it
  // tells in consecutive pieces to its argument (stopping when that returns false; it returns false then): a
  // caller that keeps them in a file (the server's cache file) writes them there and says where; the rig then
  // leaves its samples in that file as with precomputed_file. No callback keeps them where they are (in the spool,
  // else in memory); nullopt from it (the file could not be written: a full disk) reads spooled samples back into
  // memory and lets the spool go, so its disk space is not held, unseen, for as long as the rig lives.
  std::function<std::optional<PrecomputedLocation>(const PrecomputedWriter& bytes)> persist;
};

class Rig {
 public:
  // Validates and builds. Every target must have the rest shape's vertex count and faces. Throws Error
  // naming the file and the vertex or face at fault.
  static std::shared_ptr<const Rig> Build(TriangleMesh rest, std::vector<TriangleMesh> targets,
                                          const RigOptions& options = {});
  // The same for a production rig: in-betweens, combinations and masks. Errors name the target and the field
  // ("target 'jawOpen': inbetweens[1].weight = 1.5 is outside (0, 1)").
  static std::shared_ptr<const Rig> Build(TriangleMesh rest, std::vector<TargetSpec> targets,
                                          const RigOptions& options = {});
  static std::shared_ptr<const Rig> Build(TriangleMesh rest, std::vector<TargetSpec> targets,
                                          const RigOptions& options, const RigBuildControl& control);
  ~Rig();
  // What is costly to rebuild (the target paths) as versioned bytes, for RigBuildControl::precomputed.
  std::string SavePrecomputed() const;
  // The same bytes told in pieces (PrecomputedWriter), never held together.
  bool WritePrecomputed(const std::function<bool(std::string_view piece)>& write) const;
  Rig(const Rig&) = delete;
  Rig& operator=(const Rig&) = delete;

  const RigOptions& options() const { return options_; }
  const RigSummary& summary() const { return summary_; }
  int num_vertices() const { return summary_.vertices; }
  int num_surface_vertices() const { return summary_.surface_vertices; }
  // The weights a frame gives: one per target that is not a combination, in the order built.
  int num_targets() const { return static_cast<int>(target_names_.size()); }
  // The sculpted shapes besides the rest shape: the targets at weight 1 (shape t is target t), then the
  // in-betweens (by target, by weight), then the combinations' sculpts. A rig of plain targets has one each.
  int num_shapes() const { return static_cast<int>(targets_.size()); }
  // The weight of each sculpted shape (num_shapes) for a frame's target weights (num_targets, unchecked):
  // the in-betweens' piecewise-linear hat functions (extrapolated linearly outside [0, 1]), a combination's
  // product of its drivers' weights, less that product on each driver's full shape.
  std::vector<double> ShapeWeights(const std::vector<double>& weights) const;
  // Positions of every simulated vertex (#vertices by 3) in shape s: 0 is the rest shape, s + 1 sculpted
  // shape s. Rows [0, surface) are the mesh; then cap and interior vertices, placed in each shape by a solve.
  const Points& shape(int s) const { return shapes_[s]; }
  // Tetrahedra of the rest volume (positively oriented in the rest shape); empty without an interior.
  const Tetrahedra& tetrahedra() const { return tets_; }
  // The anchor: vertex ids and their rest positions' centroid.
  const std::vector<int>& anchor_vertices() const { return anchor_; }
  int num_springs() const { return static_cast<int>(spring_a_.size()); }
  const TriangleMesh& rest() const { return rest_; }
  // Sculpted shape s (masked where its target has a mask): target(t) for t < num_targets() is target t at 1.
  const TriangleMesh& target(int s) const { return targets_[s]; }
  const std::vector<std::string>& target_names() const { return target_names_; }
  const std::vector<std::string>& combination_names() const { return combination_names_; }

  // Springs: endpoints a < b, kind, and rest length in the rest shape and per target.
  const std::vector<int>& spring_a() const { return spring_a_; }
  const std::vector<int>& spring_b() const { return spring_b_; }
  const std::vector<SpringKind>& spring_kind() const { return spring_kind_; }
  const std::vector<double>& rest_lengths() const { return rest_length0_; }
  // r_q^s - r_q^0 for sculpted shape s.
  const std::vector<double>& rest_length_delta(int s) const { return rest_length_delta_[s]; }
  // Whether shape s changes any rest length at all (a weight on it can then be skipped).
  bool target_changes_lengths(int s) const { return target_changes_lengths_[s] != 0; }

  // Boundary conditions: sorted vertex indices, moved with the linear blendshape.
  const std::vector<int>& fixed_vertices() const { return fixed_vertices_; }
  BoundaryMode boundary_mode() const { return summary_.boundary_mode; }
  // For kFloating: three vertices spanning the rest shape (origin, axis, plane) used as the gauge.
  const std::array<int, 3>& gauge_vertices() const { return gauge_; }
  // Incident springs of each vertex (CSR): spring ids in [offsets[v], offsets[v+1]).
  const std::vector<int>& vertex_spring_offsets() const { return vertex_spring_offsets_; }
  const std::vector<int>& vertex_springs() const { return vertex_springs_; }

  const Eigen::Vector3d& anchor_centroid() const { return anchor_centroid_; }

  // What the solver keeps beyond the data above (the Hessian's pattern and symbolic factorization, the
  // targets' anchor motions); opaque outside the solver library.
  struct Internals;
  const Internals& internals() const { return *internals_; }

 private:
  Rig();
  friend class RigBuilder;

  RigOptions options_;
  RigSummary summary_;
  TriangleMesh rest_;
  std::vector<TriangleMesh> targets_;  // the sculpted shapes
  std::vector<std::string> target_names_, combination_names_;
  std::vector<Points> shapes_;
  Tetrahedra tets_;
  std::vector<int> anchor_;
  Eigen::Vector3d anchor_centroid_ = Eigen::Vector3d::Zero();
  std::vector<int> spring_a_, spring_b_;
  std::vector<SpringKind> spring_kind_;
  std::vector<double> rest_length0_;
  std::vector<std::vector<double>> rest_length_delta_;
  std::vector<char> target_changes_lengths_;
  std::vector<int> fixed_vertices_;
  std::array<int, 3> gauge_ = {-1, -1, -1};
  std::vector<int> vertex_spring_offsets_, vertex_springs_;
  std::unique_ptr<Internals> internals_;
};

}  // namespace springblend
