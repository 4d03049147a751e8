// `springblend blend`: load a rig from mesh files and solve one frame or a sweep locally.
#include <fmt/format.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <iostream>
#include <memory>
#include <optional>
#include <nlohmann/json.hpp>
#include <string>
#include <utility>
#include <vector>

#include "commands.h"
#include "frame_output.h"
#include "scene.h"
#include "collider_syntax.h"
#include "rig_file.h"
#include "springblend/error.h"
#include "springblend/mesh.h"
#include "springblend/rig.h"
#include "springblend/solve.h"

namespace springblend::cli {
namespace {

struct BlendArgs {
  std::string rig;
  std::string rest;
  std::vector<std::string> targets;
  std::vector<std::string> weights;  // numbers, or NAME=NUMBER
  std::string out;
  CacheTiming timing;
  int sweep = 0;
  bool linear = false;
  bool certify = false;
  std::string mix = ToString(SolveOptions{}.mix);
  std::optional<std::vector<std::string>> linear_targets;
  std::vector<int> fixed;
  double static_tolerance = RigOptions{}.static_tolerance;
  bool no_bending = false;
  bool no_interior = false;
  bool no_anchor = false;
  bool hold_outer_rim = false;
  double bending_stiffness = RigOptions{}.bending_stiffness;
  double tolerance = SolveOptions{}.residual_tolerance;
  int max_iterations = SolveOptions{}.max_iterations;
  std::string solver = "cholmod";
  std::string hessian = "true";
  std::string method = "newton";
  bool no_target_paths = false;
  bool verbose = false;
  std::vector<std::string> colliders;
  std::vector<std::string> pins;
  FramesInput input;  // --frames, --take, --map, --lost
};

nlohmann::json RigJson(const RigSummary& s) {
  nlohmann::json springs;
  for (int k = 0; k < kSpringKindCount; ++k) springs[ToString(static_cast<SpringKind>(k))] = s.springs_by_kind[k];
  return {{"vertices", s.vertices},
          {"surface_vertices", s.surface_vertices},
          {"faces", s.faces},
          {"targets", s.targets},
          {"springs", s.springs},
          {"springs_by_kind", springs},
          {"interior", s.interior},
          {"interior_reason", s.interior_reason},
          {"interior_vertices", s.interior_vertices},
          {"cap_vertices", s.cap_vertices},
          {"anchor_vertices", s.anchor_vertices},
          {"tetrahedra", s.tetrahedra},
          {"static_vertices", s.static_vertices},
          {"user_fixed_vertices", s.user_fixed_vertices},
          {"rim_vertices", s.rim_vertices},
          {"boundary_mode", ToString(s.boundary_mode)},
          {"degenerate_faces", s.degenerate_faces},
          {"boundary_edges", s.boundary_edges},
          {"hessian_nonzeros", s.hessian_nonzeros},
          {"precompute_ms", s.precompute_ms},
          {"notes", s.notes}};
}

nlohmann::json FrameJson(const Rig& rig, const SolveSummary& s, int frame, const std::vector<double>& w) {
  return {{"frame", frame},
          {"weights", w},
          {"vertices", rig.num_vertices()},
          {"springs", rig.num_springs()},
          {"converged", s.converged()},
          {"termination", ToString(s.termination)},
          {"message", s.message},
          {"newton_iterations", s.newton_iterations},
          {"factorizations", s.factorizations},
          {"projected_factorizations", s.projected_factorizations},
          {"residual", s.residual},
          {"energy", s.energy},
          {"fixed_vertices", s.fixed_vertices},
          {"pins", s.pins},
          {"contacts", s.contacts},
          {"contact_rounds", s.contact_rounds},
          {"inverted_tetrahedra", s.inverted_tetrahedra},
          {"factorize_ms", s.factorize_ms},
          {"line_search_halvings", s.line_search_halvings},
          {"minimum", ToString(s.minimum)},
          {"solve_ms", s.solve_ms}};
}

int RunBlend(const BlendArgs& args) {
  RigOptions rig_options;
  rig_options.fixed_vertices = args.fixed;
  rig_options.static_tolerance = args.static_tolerance;
  rig_options.bending_springs = !args.no_bending;
  rig_options.interior = !args.no_interior;
  rig_options.anchor = !args.no_anchor;
  rig_options.hold_outer_rim = args.hold_outer_rim;
  rig_options.bending_stiffness = args.bending_stiffness;
  rig_options.linear_solver = LinearSolverTypeFromString(args.solver);
  rig_options.target_paths = !args.no_target_paths;
  // The plain rig (the meshes, their targets and names, no physics: milliseconds to build) is all the linear
  // blendshape needs, and all it takes to check the request: a bad weight, name, scene field or collider is
  // refused before the physics is built (minutes on a production face), not after.
  RigOptions plain_options = rig_options;
  plain_options.target_paths = false;
  plain_options.interior = false;
  plain_options.shell = false;
  plain_options.anchor = false;
  const std::shared_ptr<const Rig> plain = BuildRigFromFlags(args.rig, args.rest, args.targets, plain_options);

  SolveOptions options;
  options.residual_tolerance = args.tolerance;
  options.max_iterations = args.max_iterations;
  options.use_target_paths = !args.no_target_paths;
  options.linear = args.linear;
  options.certify_minimum = args.certify;
  options.mix = MixModelFromString(args.mix);
  if (args.linear_targets) {
    options.linear_targets = *args.linear_targets;
    if (options.linear_targets->size() == 1 && options.linear_targets->front() == "none") options.linear_targets->clear();
  }
  options.method = SolveMethodFromString(args.method);
  if (args.hessian == "projected") {
    options.hessian = HessianMode::kProjected;
  } else if (args.hessian == "absolute") {
    options.hessian = HessianMode::kAbsolute;
  } else if (args.hessian != "true") {
    throw Error(ErrorCode::kInvalidInput, "--hessian must be 'true' or 'projected', got '" + args.hessian + "'");
  }
  options.Validate();

  std::vector<Frame> frames;
  std::vector<std::string> collider_specs = args.colliders;
  CacheTiming timing = args.timing;
  Scene scene;
  const bool from_file = args.input.given();
  if (from_file) {
    scene = LoadFrames(args.input, plain->target_names(), &timing);
    collider_specs.insert(collider_specs.begin(), scene.colliders.begin(), scene.colliders.end());
  } else {
    args.input.CheckTakeOptionsUnused();
  }
  std::vector<Collider> colliders;
  for (const auto& spec : collider_specs) colliders.push_back(ParseCollider(spec));
  std::vector<Pin> pins;
  for (const auto& spec : args.pins) pins.push_back(ParsePin(spec));

  std::vector<double> weights = ResolveWeights(ParseWeightItems(args.weights), plain->target_names(), "--weights");
  if (weights.empty() && plain->num_targets() == 1) weights = {1.0};
  if (weights.empty() && !from_file) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("--weights is required with {} targets (one weight per target, in order)",
                            plain->num_targets()));
  }
  if (!from_file) ValidateWeights(*plain, weights);
  const bool many = args.sweep > 0 || from_file;
  if (from_file) {
    frames = std::move(scene.frames);
  } else if (args.sweep > 0) {
    frames = SweepFrames(weights, args.sweep);
  } else {
    frames.push_back(Frame{weights});
  }
  // Every frame checked on the plain rig (pins aside: the physical rig may add interior vertices to pin).
  const auto validate = [&](const Rig& rig) {
    for (size_t i = 0; i < frames.size(); ++i) {
      try {
        ValidateFrame(rig, frames[i], collider_specs.size());
      } catch (const Error& e) {
        throw Error(e.code(), fmt::format("{}: {}", scene.FrameName(i), e.what()));
      }
    }
  };
  std::vector<std::vector<Pin>> frame_pins(frames.size());
  for (size_t i = 0; i < frames.size(); ++i) frame_pins[i] = std::exchange(frames[i].pins, {});
  validate(*plain);
  for (size_t i = 0; i < frames.size(); ++i) {
    frames[i].pins = std::move(frame_pins[i]);
    frames[i].pins.insert(frames[i].pins.end(), pins.begin(), pins.end());
  }

  // The physics (for --linear, the plain rig is the answer).
  const std::shared_ptr<const Rig> rig =
      args.linear ? plain : BuildRigFromFlags(args.rig, args.rest, args.targets, rig_options);
  if (args.verbose) std::cerr << RigJson(rig->summary()).dump() << "\n";
  validate(*rig);
  Solver solver(rig, options);
  solver.SetColliders(std::move(colliders));
  FrameOutput output(args.out, many, rig->rest().faces, static_cast<int>(rig->rest().vertices.rows()), timing);

  bool all_converged = true;
  Points positions;
  for (size_t i = 0; i < frames.size(); ++i) {
    const SolveSummary summary = solver.Solve(frames[i], &positions);
    all_converged = all_converged && summary.converged();
    output.Write(static_cast<int>(i), positions);
    std::cout << FrameJson(*rig, summary, static_cast<int>(i), frames[i].weights).dump() << std::endl;
  }
  output.Finish();
  return all_converged ? kExitOk : kExitNotConverged;
}

}  // namespace

Runner AddBlendCommand(CLI::App& app) {
  auto args = std::make_shared<BlendArgs>();
  CLI::App* cmd = app.add_subcommand(
      "blend", "solve blended shapes locally: the equilibrium of the mass-spring system whose rest "
               "lengths are blended with the weights");
  cmd->add_option("--rig", args->rig,
                  "a rig file (JSON: rest, targets with in-betweens, masks and combinations; see README) instead "
                  "of --rest and --target");
  cmd->add_option("--rest", args->rest, "rest shape (OBJ, PLY, OFF or STL)");
  cmd->add_option("--target", args->targets, "a blendshape target; repeat for more (order = weight order)");
  cmd->add_option("--weights", args->weights,
                  "one weight per target, comma separated (with --rig: per target that is not a combination, in "
                  "file order), or by name: jawOpen=0.7,mouthSmile_L=0.3 (the others 0); the rest shape gets 1 - "
                  "sum (default 1 for a single target). With --sweep: the end of the sweep")
      ->delimiter(',');
  cmd->add_option("--out", args->out,
                  "output OBJ file, or directory with --sweep/--frames; a path ending in .pc2 writes every frame "
                  "into one PC2 point cache instead (see --start-frame)")
      ->required();
  AddCacheTimingOptions(cmd, &args->timing);
  cmd->add_option("--sweep", args->sweep,
                  "solve N frames with alpha = 0 .. 1 times the weights, each alone, into "
                  "OUT/frame_0000.obj ...")
      ->check(CLI::Range(1, 100000));
  cmd->add_flag("--linear", args->linear, "output the plain linear blendshape instead (for comparison)");
  cmd->add_flag("--certify", args->certify,
                "check that each converged answer is a local minimum (one factorization of the true Hessian): the "
                "frame's JSON line says \"minimum\": \"minimum\" or \"not_a_minimum\"");
  cmd->add_option("--mix", args->mix,
                  "how a frame that moves several targets combines them: superposed (the linear blend plus each "
                  "target's own physical correction) or rest-lengths (the paper's blend of rest lengths)")
      ->capture_default_str();
  cmd->add_option("--linear-targets", args->linear_targets,
                  "with the superposed mix, targets added as linear deltas (correctives), comma-separated, or none "
                  "(default: mouthClose where the rig has it)")
      ->delimiter(',');
  cmd->add_option("--fixed", args->fixed, "vertex indices (0-based) held as boundary conditions")
      ->delimiter(',');
  cmd->add_option("--static-tolerance", args->static_tolerance,
                  "vertices moving less than this fraction of the diagonal in every target are fixed; "
                  "negative disables");
  cmd->add_flag("--no-bending", args->no_bending, "omit bending springs");
  cmd->add_flag("--no-interior", args->no_interior, "surface springs only (no tetrahedralized volume)");
  cmd->add_flag("--no-anchor", args->no_anchor, "no internal anchor (fixed vertices or the gauge hold the rig)");
  cmd->add_flag("--hold-outer-rim", args->hold_outer_rim,
                "hold an open surface's outer rim (a face mask's; its holes stay free) on the linear blend: the rig "
                "is then held whatever its targets move, so colliders and pins work");
  cmd->add_option("--bending-stiffness", args->bending_stiffness,
                  "stiffness of bending springs relative to structure springs");
  cmd->add_option("--tolerance", args->tolerance, "residual tolerance (largest force, strain units)");
  cmd->add_option("--max-iterations", args->max_iterations, "Newton iterations per frame");
  cmd->add_option("--solver", args->solver, "sparse Cholesky backend: cholmod (default; preconditions with its factor in single precision), cholmod-double, cholmod-library (CHOLMOD's own factorization, one thread), mumps (single precision) or eigen");
  cmd->add_option("--method", args->method, "equilibrium method: newton (default), newton-laplacian or lbfgs");
  cmd->add_option("--hessian", args->hessian,
                  "true (true Hessian, projected when not positive definite) or projected");
  cmd->add_flag("--no-target-paths", args->no_target_paths,
                "build no target paths and start every frame from the linear blendshape (faster to build, slower "
                "to solve; thin parts may buckle the other way)");
  cmd->add_flag("-v,--verbose", args->verbose, "print the rig summary as JSON on stderr");
  cmd->add_option("--collider", args->colliders,
                  "an obstacle: sphere:cx,cy,cz,r | capsule:x1,y1,z1,x2,y2,z2,r | box:cx,cy,cz,hx,hy,hz | "
                  "plane:px,py,pz,nx,ny,nz (solid behind the normal) | mesh:PATH (closed); repeatable");
  cmd->add_option("--pin", args->pins, "VERTEX:x,y,z holds a mesh vertex at a position in every frame; repeatable");
  AddFramesOptions(cmd, &args->input);
  return [args] { return RunBlend(*args); };
}

}  // namespace springblend::cli
