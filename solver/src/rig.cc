// A rig: the options' checks, the enums' names, and the orchestration of its build (rig_builder.h).
#include "springblend/rig.h"

#include <fmt/format.h>

#include <chrono>
#include <cmath>

#include "rig_builder.h"
#include "target_paths.h"
#include "springblend/error.h"

namespace springblend {

const char* ToString(ErrorCode code) {
  switch (code) {
    case ErrorCode::kInvalidInput: return "invalid input";
    case ErrorCode::kNotFound: return "not found";
    case ErrorCode::kNumerical: return "numerical failure";
    case ErrorCode::kInternal: return "internal error";
    case ErrorCode::kCancelled: return "cancelled";
  }
  return "unknown";
}

const char* ToString(SpringKind kind) {
  switch (kind) {
    case SpringKind::kStructure: return "structure";
    case SpringKind::kBending: return "bending";
    case SpringKind::kInternal: return "internal";
  }
  return "unknown";
}

const char* ToString(LinearSolverType type) {
  switch (type) {
    case LinearSolverType::kCholmodSupernodal: return "cholmod";
    case LinearSolverType::kCholmodDouble: return "cholmod-double";
    case LinearSolverType::kCholmodLibrary: return "cholmod-library";
    case LinearSolverType::kEigenSimplicial: return "eigen";
    case LinearSolverType::kMumpsSingle: return "mumps";
  }
  return "unknown";
}

LinearSolverType LinearSolverTypeFromString(const std::string& name) {
  if (name == "cholmod") return LinearSolverType::kCholmodSupernodal;
  if (name == "cholmod-double") return LinearSolverType::kCholmodDouble;
  if (name == "cholmod-library") return LinearSolverType::kCholmodLibrary;
  if (name == "eigen") return LinearSolverType::kEigenSimplicial;
  if (name == "mumps") return LinearSolverType::kMumpsSingle;
  throw Error(ErrorCode::kInvalidInput, "unknown linear solver '" + name + "' (use cholmod, cholmod-double, cholmod-library, mumps or eigen)");
}

const char* ToString(BoundaryMode mode) {
  switch (mode) {
    case BoundaryMode::kFixedVertices: return "fixed_vertices";
    case BoundaryMode::kPartiallyFixed: return "partially_fixed";
    case BoundaryMode::kFloating: return "floating";
    case BoundaryMode::kAnchored: return "anchored";
  }
  return "unknown";
}

void RigOptions::Validate() const {
  auto in_range = [](double v, double lo, double hi, const char* field) {
    if (!(v >= lo && v <= hi)) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("rig option {} = {} is outside [{}, {}]", field, v, lo, hi));
    }
  };
  if (!std::isfinite(static_tolerance)) {
    throw Error(ErrorCode::kInvalidInput, "rig option static_tolerance must be finite");
  }
  in_range(structure_stiffness, 1e-6, 1e6, "structure_stiffness");
  in_range(bending_stiffness, 0.0, 1e6, "bending_stiffness");
  in_range(internal_stiffness, 0.0, 1e6, "internal_stiffness");
  in_range(min_stiffness_length, 0.0, 1.0, "min_stiffness_length");
  in_range(min_rest_length_fraction, 1e-9, 0.99, "min_rest_length_fraction");
  in_range(radius_edge_ratio, 1.01, 100.0, "radius_edge_ratio");
  in_range(tetgen_timeout_seconds, 0.001, 86400.0, "tetgen_timeout_seconds");
  in_range(anchor_size, 3, 1000, "anchor_size");
  in_range(path_intervals, 1, 256, "path_intervals");
  in_range(path_extension, 0.0, 2.0, "path_extension");
  if (!(path_tolerance > 0.0 && path_tolerance <= 0.1)) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("rig option path_tolerance = {} is outside (0, 0.1]", path_tolerance));
  }
  in_range(path_max_samples, 4, 1024, "path_max_samples");
  if (!(shell_thickness > 0.0 && shell_thickness <= 100.0)) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("rig option shell_thickness = {} is outside (0, 100]", shell_thickness));
  }
  if (anchor_center && !(std::isfinite((*anchor_center)[0]) && std::isfinite((*anchor_center)[1]) &&
                         std::isfinite((*anchor_center)[2]))) {
    throw Error(ErrorCode::kInvalidInput, "rig option anchor_center must be finite");
  }
}

Rig::Rig() : internals_(std::make_unique<Internals>()) {}
Rig::~Rig() = default;


namespace {

double Elapsed(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
}

// The arrays a rig keeps besides its paths: shapes, springs with their per-shape lengths, the Hessian's
// pattern (and the symbolic factor about as large), the meshes.
std::int64_t EstimateRigBytes(const Rig& rig) {
  const std::int64_t n = rig.num_vertices(), m = rig.num_springs(), shapes = rig.num_shapes() + 1;
  return 24 * n * shapes * 2 + m * (9 + 8 * shapes) + rig.summary().hessian_nonzeros * 16 +
         rig.summary().faces * 12LL * shapes;
}

}  // namespace

std::shared_ptr<const Rig> RigBuilder::Build(TriangleMesh rest, std::vector<TargetSpec> targets,
                                             const RigOptions& options, const RigBuildControl& control) {
  const auto start = std::chrono::steady_clock::now();
  const auto stage = [&](const char* name, int targets_with_paths = 0, int done = 0, int samples = 0) {
    if (control.stop && control.stop()) throw Error(ErrorCode::kCancelled, "the rig build was cancelled");
    if (control.progress) control.progress({name, targets_with_paths, done, samples, Elapsed(start)});
  };
  options.Validate();
  ValidateMesh(rest);

  std::shared_ptr<Rig> rig(new Rig());
  rig->options_ = options;
  rig->rest_ = std::move(rest);
  RigBuilder builder(rig);
  builder.ExpandSpecs(std::move(targets));
  CheckTargets(rig->rest_, rig->targets_);
  RigSummary& s = rig->summary_;
  s.surface_vertices = static_cast<int>(rig->rest_.vertices.rows());
  s.faces = static_cast<int>(rig->rest_.faces.rows());
  s.targets = static_cast<int>(rig->targets_.size());
  s.polygons_split = rig->rest_.polygons_split;
  s.bounding_box_diagonal = BoundingBoxDiagonal(rig->rest_.vertices);
  if (!(s.bounding_box_diagonal > 0.0)) {
    throw Error(ErrorCode::kInvalidInput, rig->rest_.source + ": all vertices coincide");
  }

  stage("springs");
  builder.BuildSurfaceSprings();
  stage("interior");
  builder.BuildInterior();
  if (options.interior && options.shell && builder.interior_.path == internal::Interior::Path::kSurfaceOnly) {
    builder.BuildShell();
  }
  s.vertices = static_cast<int>(builder.interior_.vertices.rows());
  rig->shapes_.assign(rig->targets_.size() + 1, Points());
  rig->shapes_[0] = builder.interior_.vertices;
  for (size_t t = 0; t < rig->targets_.size(); ++t) rig->shapes_[t + 1] = rig->shapes_[0];
  builder.BuildIncidence();
  builder.ComputeRestLengths();
  builder.FindDegenerateFaces();
  builder.BuildBoundary();

  stage("analysis");
  Rig::Internals& internals = *rig->internals_;
  internals.pattern = std::make_unique<internal::HessianPattern>(
      internal::HessianPattern::Build(s.vertices, rig->spring_a_, rig->spring_b_));
  s.hessian_nonzeros = static_cast<std::int64_t>(internals.pattern->matrix.row_indices.size());
  internals.cholesky = internal::SparseCholesky::Create(options.linear_solver);
  internals.cholesky->Analyze(internals.pattern->matrix);

  stage("placement");
  if (s.shell_vertices > 0) {
    builder.PlaceShell();
  } else {
    builder.PlaceInterior();
  }
  builder.ComputeRestLengths();
  builder.ApplyMasks();
  if (s.boundary_mode == BoundaryMode::kFloating) {
    s.notes.push_back(
        "the rig is floating: no vertex is static in every target, none is fixed and it has no internal anchor, "
        "so frames with colliders or pins are refused; hold it by fixing vertices (fixed_vertices, --fixed) or, "
        "for an open surface such as a face mask, by holding its outer rim (hold_outer_rim, --hold-outer-rim)");
  }
  s.rig_bytes = EstimateRigBytes(*rig);
  if (options.target_paths) {
    std::string why;
    // The paths at a file's location, their samples left there; nullopt and why when they are not this rig's.
    const auto parse_file = [&](const PrecomputedLocation& at, std::string* why_not) {
      try {
        return internal::ParseTargetPaths(internal::PathFile::Open(at.file, at.opened ? at.opened->fd() : -1), at.offset, at.size, rig->num_targets(),
                                          s.vertices, why_not);
      } catch (const Error& e) {
        *why_not = e.what();
        return std::optional<std::vector<internal::TargetPath>>();
      }
    };
    if (control.precomputed != nullptr || control.precomputed_file) {
      std::optional<std::vector<internal::TargetPath>> paths;
      if (control.precomputed != nullptr) {
        paths = internal::ParseTargetPaths(*control.precomputed, rig->num_targets(), s.vertices, &why);
      } else {
        paths = parse_file(*control.precomputed_file, &why);
      }
      if (paths) {
        internals.paths = std::move(*paths);
        s.paths_loaded = true;
      } else {
        s.notes.push_back("the precomputed target paths were not used (" + why + "): solved again");
      }
    }
    if (!s.paths_loaded) {
      int with_path = 0;
      for (int t = 0; t < rig->num_targets(); ++t) with_path += internal::TargetChangesLengths(*rig, t) ? 1 : 0;
      stage("paths", with_path);
      internal::TargetPathsOptions path_options;
      path_options.intervals = options.path_intervals;
      path_options.extension = options.path_extension;
      path_options.tolerance = options.path_tolerance;
      path_options.max_samples = options.path_max_samples;
      path_options.stop = control.stop ? &control.stop : nullptr;
      if (!control.spool_directory.empty()) {
        try {
          path_options.spool = internal::PathFile::Spool(control.spool_directory);
        } catch (const Error& e) {
          s.notes.push_back(
              fmt::format("the target paths were held in memory while they were solved ({})", e.what()));
        }
      }
      int done = 0, samples = 0;
      if (control.progress) {
        path_options.done = [&](int, const internal::TargetPath& path) {
          ++done;
          samples += path.samples();
          control.progress({"paths", with_path, done, samples, Elapsed(start)});
        };
      }
      internal::TargetPathsReport report;
      internals.paths = internal::BuildTargetPaths(*rig, path_options, &report);
      s.unconverged_path_samples = report.unconverged;
      s.path_ms = report.ms;
      if (!report.spool_error.empty()) {
        s.notes.push_back(fmt::format("some target paths were held in memory: {}", report.spool_error));
      }
      if (report.unconverged > 0) {
        s.notes.push_back(fmt::format("{} of {} samples of the targets' paths did not converge; frames near them "
                                      "start from the best found",
                                      report.unconverged, report.samples));
      }
      if (control.persist) {
        // Kept in the caller's file: the samples are read from there from now on, the same bits.
        const std::vector<internal::TargetPath>& solved = internals.paths;
        const PrecomputedWriter bytes = [&solved](const std::function<bool(std::string_view)>& write) {
          return internal::WriteTargetPaths(solved, write);
        };
        const std::optional<PrecomputedLocation> at = control.persist(bytes);
        if (!at && path_options.spool) {
          // Not kept (a full disk, no descriptor left): the spool must not hold its disk space for as long as the
          // rig lives, unseen in the directory. The samples come back into memory (counted in path_bytes), and
          // the spool goes with the last field that read it.
          for (internal::TargetPath& path : internals.paths) {
            for (internal::PathField& c : path.corrections) c.Load();
            for (internal::PathField& d : path.tangents) d.Load();
          }
          path_options.spool.reset();
        }
        if (at) {
          std::string why_not;
          std::optional<std::vector<internal::TargetPath>> stored = parse_file(*at, &why_not);
          if (stored && stored->size() == internals.paths.size()) {
            for (size_t t = 0; t < stored->size(); ++t) {
              internal::TargetPath& path = internals.paths[t];
              if ((*stored)[t].samples() != path.samples()) continue;  // (cannot happen: the same bytes)
              path.corrections = std::move((*stored)[t].corrections);
              path.tangents = std::move((*stored)[t].tangents);
            }
          } else {
            s.notes.push_back(fmt::format("the target paths could not be left in '{}' ({}): {}", at->file,
                                          why_not.empty() ? "another rig's" : why_not,
                                          path_options.spool ? "read from the build's spool" : "held in memory"));
          }
        }
      }
    }
    for (size_t t = 0; t < internals.paths.size(); ++t) {
      const internal::TargetPath& path = internals.paths[t];
      if (path.empty()) continue;
      s.path_samples += path.samples();
      s.path_solves += path.solves;
      s.uncertified_path_intervals += path.uncertified();
      s.path_max_error = std::max(s.path_max_error, path.max_error);
      s.path_bytes += path.bytes();
      s.path_file_bytes += path.stored_bytes();
      s.paths.push_back({rig->target_names_[t], path.samples(), path.solves, path.uncertified(), path.max_error,
                         s.paths_loaded ? 0.0 : path.build_ms, path.checks, path.local_checks,
                         path.UncertifiedRanges()});
    }
    if (s.uncertified_path_intervals > 0) {
      s.notes.push_back(fmt::format(
          "{} intervals of the targets' paths are not certified within {} samples per target (frames there start "
          "farther from their answer and may need a full solve)",
          s.uncertified_path_intervals, options.path_max_samples));
    }
  }
  if (s.boundary_mode == BoundaryMode::kFloating) {
    s.notes.push_back(fmt::format(
        "no boundary condition and no anchor: solved in the frame of vertices {}, {}, {} (a 3-2-1 gauge that "
        "adds no force) and rigidly aligned onto the linear blendshape",
        rig->gauge_[0], rig->gauge_[1], rig->gauge_[2]));
  }
  s.precompute_ms = Elapsed(start);
  stage("done", 0, 0, s.path_samples);
  return rig;
}

std::string Rig::SavePrecomputed() const { return internal::SerializeTargetPaths(internals_->paths); }

bool Rig::WritePrecomputed(const std::function<bool(std::string_view piece)>& write) const {
  return internal::WriteTargetPaths(internals_->paths, write);
}

std::shared_ptr<const Rig> Rig::Build(TriangleMesh rest, std::vector<TriangleMesh> targets,
                                      const RigOptions& options) {
  std::vector<TargetSpec> specs(targets.size());
  for (size_t t = 0; t < targets.size(); ++t) {
    specs[t].name = targets[t].name;
    specs[t].mesh = std::move(targets[t]);
  }
  return RigBuilder::Build(std::move(rest), std::move(specs), options, {});
}

std::shared_ptr<const Rig> Rig::Build(TriangleMesh rest, std::vector<TargetSpec> targets,
                                      const RigOptions& options) {
  return RigBuilder::Build(std::move(rest), std::move(targets), options, {});
}

std::shared_ptr<const Rig> Rig::Build(TriangleMesh rest, std::vector<TargetSpec> targets, const RigOptions& options,
                                      const RigBuildControl& control) {
  return RigBuilder::Build(std::move(rest), std::move(targets), options, control);
}

}  // namespace springblend
