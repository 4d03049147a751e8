// springblend-bench: per row (the paper's Table 1 characters) and per solve method, on the same frames of the
// paper's sweep (N frames from the rest shape to the target, SweepFrames: frame 0 is alpha 0):
//   - every frame 1..N-1 solved alone, by a fresh Solver (median, p95, max ms), and the frames solved in order
//     by one Solver (median ms per step); frames are stateless, so the two differ only by what a Solver builds
//     on first use (the Laplacian's factor of newton-laplacian and lbfgs) and by warm caches;
//   - iterations and the time split per frame, from the alone pass;
//   - accuracy against a tightly converged reference of the same frames (direct Newton, 1e-12);
//   - the direct-Newton baseline (a fresh factorization and a direct solve per Newton iteration), alone, and
//     every method's speed-up over it;
//   - the upload (rig build and its path part), the rig's memory (resident-set growth over the build) and the
//     row's peak resident set;
// and, after the tables, the cost-growth exponent (least-squares slope of log ms per frame alone of the first
// method against log vertices). Writes OUT/bench.md, OUT/bench.json (every frame's summary) and a plot of ms
// per frame (first method, alone) with gnuplot when installed, and prints the Markdown.
#include <fmt/format.h>
#include <malloc.h>
#include <sys/resource.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <cstdlib>
#include <ctime>
#include <exception>
#include <filesystem>
#include <functional>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "process_memory.h"
#include "springblend/error.h"
#include "springblend/mesh.h"
#include "springblend/rig.h"
#include "springblend/runtime.h"
#include "springblend/solve.h"

namespace springblend::bench {
namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;
using nlohmann::json;

double MsSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

// ---- Solver configurations -------------------------------------------------------------------------------

// --residual-tolerance / --step-tolerance override the measured methods' (and the baseline's) tolerances.
std::optional<double> g_residual_tolerance, g_step_tolerance;
// --negative-curvature on|off: override SolveOptions::follow_negative_curvature (every configuration).
std::optional<bool> g_follow_negative_curvature;
// --mix-start scaled|summed: override SolveOptions::scale_mix_start (every configuration).
std::optional<bool> g_scale_mix_start;
// --mix superposed|rest-lengths: override SolveOptions::mix (every configuration).
std::optional<MixModel> g_mix;
// --linear-solver: the rigs' sparse Cholesky backend (RigOptions::linear_solver).
LinearSolverType g_linear_solver = RigOptions{}.linear_solver;
// --precomputed DIR: each row's target paths kept in DIR/<row>-<backend>.precomputed (Rig::SavePrecomputed) and
// reused by later runs, so a run that measures frames need not solve the paths again (the upload column then
// measures a restart).
fs::path g_precomputed_dir;
SolveOptions WithTolerances(SolveOptions options) {
  if (g_residual_tolerance) options.residual_tolerance = *g_residual_tolerance;
  if (g_step_tolerance) options.step_tolerance = *g_step_tolerance;
  if (g_follow_negative_curvature) options.follow_negative_curvature = *g_follow_negative_curvature;
  if (g_scale_mix_start) options.scale_mix_start = *g_scale_mix_start;
  if (g_mix) options.mix = *g_mix;
  return options;
}

// A measured configuration: a solve method with the shipped options, or the baseline.
struct Config {
  std::string name;
  SolveOptions options;
  bool baseline = false;
};

Config MethodConfig(const std::string& method) {
  SolveOptions options;
  options.method = SolveMethodFromString(method);
  // Every answer certified (a factorization of the true Hessian at it, timed apart from the frame).
  options.certify_minimum = true;
  return {ToString(options.method), WithTolerances(options), false};
}

// The "direct Newton" baseline the speed-up is measured against, on the same frames from the same start:
// the paper's method, a fresh factorization and a direct solve in every Newton iteration (same line search
// and Hessian choice as the default solver).
Config BaselineConfig() {
  SolveOptions options;
  options.reuse_factorization = false;
  options.certify_minimum = true;
  return {"direct-newton", WithTolerances(options), true};
}

// The reference every frame is compared with: direct Newton converged far below the default tolerances.
SolveOptions ReferenceOptions() {
  SolveOptions options;
  options.reuse_factorization = false;
  options.residual_tolerance = 1e-12;
  options.step_tolerance = 1e-12;
  return options;
}

// ---- Rows ------------------------------------------------------------------------------------------------

// The paper's Table 1 figure for the same character (2.66 GHz Core 2 Quad, PARDISO, CPU column).
struct PaperFigure {
  double cpu_s_per_step = 0.0;
  double vertices_k = 0.0;  // including internal and anchor vertices
  double springs_k = 0.0;
};

struct RowSpec {
  std::string name;  // the --rows key
  fs::path dir;
  std::string rest;
  std::vector<std::string> targets;
  std::vector<double> end_weights;  // one per target: the weights of the sweep's last frame
  std::optional<PaperFigure> paper;
};

// A row of three of `pool`'s targets, drawn without repeats, and end weights w_i = s u_i / sum u (u_i in
// [0.5, 1], the mix's total s in [0.6, 1], so the rest shape keeps a non-negative weight), from a generator
// seeded by the row's name: the same row every run and on every machine (std::mt19937 is specified).
RowSpec RandomMix(const std::string& name, const fs::path& dir, const std::string& rest,
                  std::vector<std::string> pool, std::optional<PaperFigure> paper) {
  std::seed_seq seed(name.begin(), name.end());
  std::mt19937 random(seed);
  const auto uniform = [&](double lo, double hi) {
    return lo + (hi - lo) * (static_cast<double>(random() - std::mt19937::min()) /
                             static_cast<double>(std::mt19937::max() - std::mt19937::min()));
  };
  RowSpec spec{name, dir, rest, {}, {}, paper};
  double sum = 0.0;
  for (int k = 0; k < 3 && !pool.empty(); ++k) {
    const size_t pick = static_cast<size_t>(random() % pool.size());
    spec.targets.push_back(pool[pick]);
    pool.erase(pool.begin() + static_cast<std::ptrdiff_t>(pick));
    spec.end_weights.push_back(uniform(0.5, 1.0));
    sum += spec.end_weights.back();
  }
  const double total = uniform(0.6, 1.0);
  for (double& w : spec.end_weights) w *= total / sum;
  return spec;
}

std::vector<RowSpec> AllRows(const fs::path& repo, const fs::path& shared) {
  const fs::path data = repo / "tests" / "data";
  const PaperFigure face{40.11, 8.1, 65.1};
  return {
      {"cylinder", data / "cylinder", "cylinder.obj", {"poses-2_cylinder-1.obj"}, {1.0}, std::nullopt},
      {"cube", data / "cube", "cube.obj", {"poses-1_cube-4.obj"}, {1.0}, std::nullopt},
      {"cheburashka", data / "cheburashka", "cheburashka.obj", {"poses-1_cheburashka-1.obj"}, {1.0},
       std::nullopt},
      {"face", shared / "face6706", "generic_neutral_mesh.obj", {"jawOpen.obj"}, {1.0}, face},
      // Delta weights of a face rig: the neutral takes 1 - sum, as Frame documents.
      {"face-mix",
       shared / "face6706",
       "generic_neutral_mesh.obj",
       {"jawOpen.obj", "mouthSmile_L.obj", "mouthSmile_R.obj", "eyeBlink_L.obj", "browInnerUp_L.obj"},
       {0.6, 0.5, 0.5, 0.8, 0.7},
       face},
      {"horse", shared / "horse", "horse-reference.obj", {"horse-01.obj"}, {1.0}, PaperFigure{81.36, 8.5, 96.1}},
      {"cat", shared / "cat", "cat-reference.obj", {"cat-01.obj"}, {1.0}, PaperFigure{67.58, 7.3, 81.7}},
      // Random mixes (the mixes issue: more than the five-expression face): three targets and their end
      // weights drawn from a generator seeded by the row's name, the same every run.
      RandomMix("face-random", shared / "face6706", "generic_neutral_mesh.obj",
                {"jawOpen.obj", "mouthSmile_L.obj", "mouthSmile_R.obj", "eyeBlink_L.obj", "eyeBlink_R.obj",
                 "browInnerUp_L.obj", "browInnerUp_R.obj", "browDown_L.obj", "browDown_R.obj", "cheekPuff_L.obj",
                 "cheekPuff_R.obj"},
                face),
      RandomMix("horse-random", shared / "horse", "horse-reference.obj",
                {"horse-01.obj", "horse-02.obj", "horse-03.obj", "horse-04.obj", "horse-05.obj", "horse-06.obj",
                 "horse-07.obj", "horse-08.obj", "horse-09.obj", "horse-10.obj"},
                PaperFigure{81.36, 8.5, 96.1}),
      RandomMix("cat-random", shared / "cat", "cat-reference.obj",
                {"cat-01.obj", "cat-02.obj", "cat-03.obj", "cat-04.obj", "cat-05.obj", "cat-06.obj", "cat-07.obj",
                 "cat-08.obj", "cat-09.obj"},
                PaperFigure{67.58, 7.3, 81.7}),
  };
}

// The first of the row's files that does not exist, if any.
std::optional<fs::path> MissingFile(const RowSpec& spec) {
  std::vector<std::string> files = spec.targets;
  files.insert(files.begin(), spec.rest);
  for (const auto& file : files) {
    if (!fs::is_regular_file(spec.dir / file)) return spec.dir / file;
  }
  return std::nullopt;
}

// ---- Memory ----------------------------------------------------------------------------------------------

// StatusMb and ResetPeakRss: process_memory.h.

double MaxRssMb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_maxrss) / 1024.0;
}

// ---- Measurements ----------------------------------------------------------------------------------------

double Median(std::vector<double> values) {
  if (values.empty()) return 0.0;
  std::sort(values.begin(), values.end());
  const size_t n = values.size();
  return n % 2 == 1 ? values[n / 2] : 0.5 * (values[n / 2 - 1] + values[n / 2]);
}

// Nearest-rank percentile (p in (0, 100]).
double Percentile(std::vector<double> values, double p) {
  if (values.empty()) return 0.0;
  std::sort(values.begin(), values.end());
  const auto rank = static_cast<size_t>(std::ceil(p / 100.0 * static_cast<double>(values.size())));
  return values[std::clamp<size_t>(rank, 1, values.size()) - 1];
}

// One pass over frames: each frame's index in the sweep, wall time of its Solve call (alone: with the fresh
// Solver's construction), and summary.
struct Pass {
  std::vector<int> frame;
  std::vector<double> ms;
  std::vector<SolveSummary> summaries;
  double accuracy = 0.0;  // max over the pass's frames of the max vertex distance to the reference / diagonal
  bool has_accuracy = false;
  double start_error = 0.0;  // alone: max over frames of the start's (Solver::Start) distance to the reference
  // alone: frames certified local minima (SolveOptions::certify_minimum) of those converged, and continuity: the
  // largest distance between consecutive frames over the linear blend's distance between them.
  int minima = 0, converged = 0;
  double continuity = 0.0;
  std::vector<Points> positions;  // each frame's answer (surface), in the order of `frame`

  // Figures over the sweep's frames 1..N-1 (frame 0, the rest shape, only starts a sweep).
  std::vector<double> StepMs() const {
    std::vector<double> out;
    for (size_t i = 0; i < ms.size(); ++i) {
      if (frame[i] > 0) out.push_back(ms[i]);
    }
    return out;
  }
  template <typename F>
  double MeanOverSteps(F&& value) const {
    double sum = 0.0;
    int count = 0;
    for (size_t i = 0; i < summaries.size(); ++i) {
      if (frame[i] > 0) {
        sum += static_cast<double>(value(summaries[i]));
        ++count;
      }
    }
    return count > 0 ? sum / count : 0.0;
  }
  std::map<Termination, int> Terminations() const {
    std::map<Termination, int> counts;
    for (const SolveSummary& s : summaries) ++counts[s.termination];
    return counts;
  }
  bool all_converged() const {
    return std::all_of(summaries.begin(), summaries.end(),
                       [](const SolveSummary& s) { return s.termination == Termination::kConverged; });
  }
};

struct MethodResult {
  Config config;
  std::optional<Pass> alone, sweep;

  std::optional<double> accuracy() const {
    std::optional<double> worst;
    for (const auto* pass : {&alone, &sweep}) {
      if (*pass && (*pass)->has_accuracy) worst = std::max(worst.value_or(0.0), (*pass)->accuracy);
    }
    return worst;
  }
  // The worst frame's start (the rig's prediction) against the reference, from the alone pass.
  std::optional<double> start_error() const {
    if (alone && alone->has_accuracy) return alone->start_error;
    return std::nullopt;
  }
  bool ok() const { return (!alone || alone->all_converged()) && (!sweep || sweep->all_converged()); }
  // Frames whose answer alone (a fresh Solver) and in the sweep (after the frames before it) are the same to
  // the bit: a frame's answer is a function of its request alone. Empty without both passes.
  std::optional<std::pair<int, int>> same_alone_and_in_order() const {
    if (!alone || !sweep) return std::nullopt;
    int same = 0, compared = 0;
    for (size_t i = 0; i < alone->frame.size(); ++i) {
      const size_t k = static_cast<size_t>(alone->frame[i]);
      if (k >= sweep->positions.size() || i >= alone->positions.size()) continue;
      ++compared;
      const Points& a = alone->positions[i];
      const Points& b = sweep->positions[k];
      same += a.rows() == b.rows() && std::memcmp(a.data(), b.data(), sizeof(double) * a.size()) == 0 ? 1 : 0;
    }
    return std::make_pair(same, compared);
  }
};

struct RowResult {
  std::string name;
  std::optional<PaperFigure> paper;
  std::string sweep_end;  // the sweep's last frame: each target with its weight
  bool skipped = false;
  bool failed = false;  // an exception ended the row; what was measured before it is kept
  std::string note;
  std::optional<RigSummary> rig;
  double build_ms = 0.0;
  std::optional<double> rig_mb;       // resident-set growth over Rig::Build (an estimate of the rig's size)
  std::optional<double> peak_rss_mb;  // the row's peak resident set (VmHWM after a reset), or the process's
  bool peak_is_row = false;
  double max_rss_mb = 0.0;  // getrusage ru_maxrss after the row (the process's peak so far)
  std::optional<Pass> reference;
  std::vector<MethodResult> methods;  // the measured methods in --method order, then the baseline
  std::optional<double> linear_ms;    // linear blendshape, median per frame

  const MethodResult* baseline() const {
    for (const MethodResult& m : methods) {
      if (m.config.baseline) return &m;
    }
    return nullptr;
  }
  bool ok() const {
    return !failed && std::all_of(methods.begin(), methods.end(), [](const MethodResult& m) { return m.ok(); });
  }
};

struct Settings {
  std::vector<std::string> rows;  // empty: every row
  std::vector<std::string> methods = {"newton", "newton-laplacian", "lbfgs"};
  int steps = 36;
  bool quick = false;    // also: no reference, so no accuracy column
  bool profile = false;  // only the first method's sweep: no alone pass, baseline or reference (perf record)
  fs::path repo = SPRINGBLEND_SOURCE_DIR;
  fs::path shared;  // default: <repo>/../shared/meshes
  fs::path out = "bench-results";
};

std::string LogLine(const std::string& what, int frame, int frames, double ms, const SolveSummary& s) {
  return fmt::format(
      "  {} frame {}/{}: {:.1f} ms, {} Newton, {} CG, {} L-BFGS, {} fallbacks, {} factorizations; split spring "
      "{:.1f} solve {:.1f} search {:.1f} factor {:.1f} ms; {}\n",
      what, frame, frames - 1, ms, s.newton_iterations, s.cg_iterations, s.lbfgs_iterations, s.newton_fallbacks,
      s.factorizations, s.spring_ms, s.linear_solve_ms, s.line_search_ms, s.factorize_ms, ToString(s.termination));
}

// Compares one frame's surface positions with the reference's, relative to the diagonal.
double Distance(const Points& a, const Points& b, double diagonal) {
  return (a - b).rowwise().norm().maxCoeff() / diagonal;
}

// Frames solved in order by one Solver (frame_ids: which of `frames`); keeps positions in *positions when
// given, compares with *reference when given (indexed like `frames`).
Pass SweepPass(const std::shared_ptr<const Rig>& rig, const SolveOptions& options, const std::vector<Frame>& frames,
               const std::string& what, const std::vector<Points>* reference, std::vector<Points>* positions) {
  Solver solver(rig, options);
  Pass pass;
  Points frame_positions;
  const double diagonal = BoundingBoxDiagonal(rig->rest().vertices);
  for (size_t i = 0; i < frames.size(); ++i) {
    const auto start = Clock::now();
    const SolveSummary summary = solver.Solve(frames[i], &frame_positions);
    pass.ms.push_back(MsSince(start) - summary.certify_ms);
    pass.frame.push_back(static_cast<int>(i));
    pass.summaries.push_back(summary);
    pass.positions.push_back(frame_positions);
    if (positions != nullptr) positions->push_back(frame_positions);
    if (reference != nullptr) {
      pass.accuracy = std::max(pass.accuracy, Distance(frame_positions, (*reference)[i], diagonal));
      pass.has_accuracy = true;
    }
    std::cerr << LogLine(what, static_cast<int>(i), static_cast<int>(frames.size()), pass.ms.back(), summary);
  }
  return pass;
}

// Frames 1..N-1, each by a fresh Solver (its construction and first-use setup included in the time).
Pass AlonePass(const std::shared_ptr<const Rig>& rig, const SolveOptions& options, const std::vector<Frame>& frames,
               const std::string& what, const std::vector<Points>* reference) {
  Pass pass;
  Points frame_positions;
  const double diagonal = BoundingBoxDiagonal(rig->rest().vertices);
  Points last = rig->rest().vertices, last_linear = rig->rest().vertices;  // frame 0 is the rest shape
  for (size_t i = 1; i < frames.size(); ++i) {
    const auto start = Clock::now();
    Solver solver(rig, options);
    const SolveSummary summary = solver.Solve(frames[i], &frame_positions);
    pass.ms.push_back(MsSince(start) - summary.certify_ms);
    pass.frame.push_back(static_cast<int>(i));
    pass.summaries.push_back(summary);
    pass.positions.push_back(frame_positions);
    if (summary.termination == Termination::kConverged) {
      ++pass.converged;
      pass.minima += summary.minimum == MinimumCheck::kMinimum ? 1 : 0;
    }
    const Points linear = LinearBlend(*rig, frames[i].weights);
    const double moved = Distance(linear, last_linear, 1.0);
    if (moved > 0.0) pass.continuity = std::max(pass.continuity, Distance(frame_positions, last, 1.0) / moved);
    last = frame_positions;
    last_linear = linear;
    if (reference != nullptr) {
      pass.accuracy = std::max(pass.accuracy, Distance(frame_positions, (*reference)[i], diagonal));
      pass.has_accuracy = true;
      const Points start_positions = solver.Start(frames[i].weights).topRows(rig->num_surface_vertices());
      const double start_error = Distance(start_positions, (*reference)[i], diagonal);
      pass.start_error = std::max(pass.start_error, start_error);
      std::cerr << fmt::format("  {} frame {}: start {:.2e} from the reference, answer {:.2e}\n", what, i,
                               start_error, Distance(frame_positions, (*reference)[i], diagonal));
    }
    std::cerr << LogLine(what, static_cast<int>(i), static_cast<int>(frames.size()), pass.ms.back(), summary);
  }
  return pass;
}

double LinearBlendMedianMs(const Rig& rig, const std::vector<Frame>& frames) {
  std::vector<double> ms;
  for (size_t i = 1; i < frames.size(); ++i) {
    const auto start = Clock::now();
    LinearBlend(rig, frames[i].weights);
    ms.push_back(MsSince(start));
  }
  return Median(ms);
}

std::shared_ptr<const Rig> BuildRig(const RowSpec& spec, RowResult* result) {
  TriangleMesh rest = LoadMesh((spec.dir / spec.rest).string());
  std::vector<TriangleMesh> targets;
  for (const auto& target : spec.targets) targets.push_back(LoadMesh((spec.dir / target).string()));
  malloc_trim(0);
  const std::optional<double> before = StatusMb("VmRSS");
  const auto start = Clock::now();
  RigOptions rig_options;
  rig_options.linear_solver = g_linear_solver;
  std::string saved;
  const fs::path saved_path =
      g_precomputed_dir.empty() ? fs::path() : g_precomputed_dir / (spec.name + "-" + ToString(g_linear_solver) + ".precomputed");
  if (!saved_path.empty() && fs::exists(saved_path)) {
    std::ifstream in(saved_path, std::ios::binary);
    saved.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  std::vector<TargetSpec> specs;
  for (auto& target : targets) {
    TargetSpec target_spec;
    target_spec.name = target.name;
    target_spec.mesh = std::move(target);
    specs.push_back(std::move(target_spec));
  }
  RigBuildControl control;
  if (!saved.empty()) control.precomputed = &saved;
  auto rig = Rig::Build(std::move(rest), std::move(specs), rig_options, control);
  result->build_ms = MsSince(start);
  if (!saved_path.empty() && !rig->summary().paths_loaded) {
    fs::create_directories(g_precomputed_dir);
    std::ofstream(saved_path, std::ios::binary) << rig->SavePrecomputed();
  }
  malloc_trim(0);
  const std::optional<double> after = StatusMb("VmRSS");
  // The meshes moved into the rig were counted before the build; the rest is what the build added.
  if (before && after) result->rig_mb = std::max(0.0, *after - *before);
  result->rig = rig->summary();
  return rig;
}

// Fills *result step by step, so whatever was measured before an exception stays in the report, and calls
// checkpoint after every pass (the reports are then rewritten, so a run that is stopped keeps its passes).
void MeasureRow(const RowSpec& spec, const Settings& settings, RowResult* result,
                const std::function<void()>& checkpoint) {
  std::cerr << fmt::format("[{}] building the rig\n", spec.name);
  const auto rig = BuildRig(spec, result);
  std::cerr << fmt::format("[{}] rig built in {:.0f} ms ({:.0f} ms of paths), {} vertices\n", spec.name,
                           result->build_ms, result->rig->path_ms, result->rig->vertices);
  const std::vector<Frame> frames = SweepFrames(spec.end_weights, settings.steps);
  if (settings.profile) {
    const Config config = MethodConfig(settings.methods.front());
    result->methods.push_back({config, std::nullopt, SweepPass(rig, config.options, frames,
                                                               spec.name + " " + config.name + " sweep", nullptr,
                                                               nullptr)});
    return;
  }
  std::vector<Points> reference_positions;
  const std::vector<Points>* reference = nullptr;
  if (!settings.quick) {
    result->reference =
        SweepPass(rig, ReferenceOptions(), frames, spec.name + " reference", nullptr, &reference_positions);
    reference = &reference_positions;
    if (!result->reference->all_converged()) result->note = "reference not fully converged";
    checkpoint();
  }
  std::vector<Config> configs;
  for (const std::string& method : settings.methods) configs.push_back(MethodConfig(method));
  configs.push_back(BaselineConfig());
  for (const Config& config : configs) {
    result->methods.push_back({config, std::nullopt, std::nullopt});
    MethodResult& m = result->methods.back();
    m.alone = AlonePass(rig, config.options, frames, spec.name + " " + config.name + " alone", reference);
    checkpoint();
    // The baseline is measured alone only (it is the slowest configuration, and the speed-up uses alone).
    if (!config.baseline) {
      m.sweep = SweepPass(rig, config.options, frames, spec.name + " " + config.name + " sweep", reference,
                          nullptr);
      checkpoint();
    }
  }
  result->linear_ms = LinearBlendMedianMs(*rig, frames);
}

void RunRow(const RowSpec& spec, const Settings& settings, RowResult& result,
            const std::function<void()>& checkpoint) {
  result.name = spec.name;
  for (size_t t = 0; t < spec.targets.size(); ++t) {
    result.sweep_end += fmt::format("{}{} {:.3f}", t == 0 ? "" : ", ", spec.targets[t], spec.end_weights[t]);
  }
  result.paper = spec.paper;
  if (const auto missing = MissingFile(spec)) {
    result.skipped = true;
    result.note = "skipped: missing " + missing->string();
    return;
  }
  result.peak_is_row = ResetPeakRss();
  constexpr const char* kIncomplete = "incomplete: stopped while measuring";
  result.note = kIncomplete;  // what a report written before the row ends says
  try {
    MeasureRow(spec, settings, &result, [&] {
      result.max_rss_mb = MaxRssMb();
      result.peak_rss_mb = result.peak_is_row ? StatusMb("VmHWM") : std::optional<double>(result.max_rss_mb);
      checkpoint();
    });
    if (result.note == kIncomplete) result.note.clear();
  } catch (const Error& e) {
    result.failed = true;
    result.note = fmt::format("error ({}): {}", ToString(e.code()), e.what());
  } catch (const std::exception& e) {
    result.failed = true;
    result.note = fmt::format("internal error: {}", e.what());
  }
  result.max_rss_mb = MaxRssMb();
  result.peak_rss_mb = result.peak_is_row ? StatusMb("VmHWM") : std::optional<double>(result.max_rss_mb);
}

// ---- Machine description ---------------------------------------------------------------------------------

std::string CommandOutput(const std::string& command) {
  std::string output;
  if (FILE* pipe = popen(command.c_str(), "r")) {
    std::array<char, 256> buffer;
    while (fgets(buffer.data(), static_cast<int>(buffer.size()), pipe) != nullptr) output += buffer.data();
    pclose(pipe);
  }
  while (!output.empty() && (output.back() == '\n' || output.back() == ' ')) output.pop_back();
  return output;
}

std::string CpuModel() {
  std::ifstream cpuinfo("/proc/cpuinfo");
  std::string line;
  while (std::getline(cpuinfo, line)) {
    const size_t colon = line.find(':');
    if (line.rfind("model name", 0) == 0 && colon != std::string::npos) return line.substr(colon + 2);
  }
  return "unknown CPU";
}

std::string UtcNow() {
  const std::time_t now = std::time(nullptr);
  std::tm utc{};
  gmtime_r(&now, &utc);
  std::array<char, 32> text;
  std::strftime(text.data(), text.size(), "%Y-%m-%d %H:%M UTC", &utc);
  return text.data();
}

struct Machine {
  unsigned nproc = std::thread::hardware_concurrency();
  std::string cpu = CpuModel();
  std::string date = UtcNow();
  std::string git;
};

Machine DescribeMachine(const fs::path& repo) {
  Machine machine;
  machine.git = CommandOutput(fmt::format("git -C '{}' describe --always --dirty 2>/dev/null", repo.string()));
  if (machine.git.empty()) machine.git = "n/a";
  return machine;
}

// ---- Cost growth -----------------------------------------------------------------------------------------

struct Growth {
  double exponent = 0.0;
  std::vector<std::pair<std::string, std::pair<int, double>>> points;  // row, (vertices, ms)
};

// Least-squares slope of log(ms per frame alone, first method, median) against log(vertices) over the rows
// measured; nullopt with fewer than two distinct vertex counts.
std::optional<Growth> CostGrowth(const std::vector<RowResult>& rows) {
  Growth growth;
  for (const RowResult& row : rows) {
    if (!row.rig || row.methods.empty() || !row.methods.front().alone) continue;
    const double ms = Median(row.methods.front().alone->StepMs());
    if (ms > 0.0) growth.points.push_back({row.name, {row.rig->vertices, ms}});
  }
  double mx = 0.0, my = 0.0;
  for (const auto& [name, p] : growth.points) {
    mx += std::log(p.first);
    my += std::log(p.second);
  }
  const double n = static_cast<double>(growth.points.size());
  if (n < 2) return std::nullopt;
  mx /= n;
  my /= n;
  double sxx = 0.0, sxy = 0.0;
  for (const auto& [name, p] : growth.points) {
    sxx += (std::log(p.first) - mx) * (std::log(p.first) - mx);
    sxy += (std::log(p.first) - mx) * (std::log(p.second) - my);
  }
  if (sxx <= 0.0) return std::nullopt;
  growth.exponent = sxy / sxx;
  return growth;
}

// ---- Markdown --------------------------------------------------------------------------------------------

template <typename T, typename Format>
std::string Cell(const std::optional<T>& value, Format&& format) {
  return value ? format(*value) : "-";
}

std::string TerminationCell(const MethodResult& m) {
  std::map<Termination, int> counts;
  for (const auto* pass : {&m.alone, &m.sweep}) {
    if (*pass) {
      for (const auto& [t, c] : (*pass)->Terminations()) counts[t] += c;
    }
  }
  std::vector<std::string> parts;
  for (const auto& [termination, count] : counts) parts.push_back(fmt::format("{} {}", ToString(termination), count));
  return fmt::format("{}", fmt::join(parts, ", "));
}

// A note as one Markdown cell: no pipes, no line breaks.
std::string Escape(const std::string& text) {
  std::string escaped;
  for (const char c : text) {
    if (c == '|') {
      escaped += "\\|";
    } else {
      escaped += c == '\n' ? ' ' : c;
    }
  }
  return escaped;
}

std::string Header(const std::vector<std::string>& columns) {
  return fmt::format("| {} |\n|{}\n", fmt::join(columns, " | "),
                     fmt::join(std::vector<std::string>(columns.size(), "---|"), ""));
}

const std::vector<std::string> kRowColumns = {
    "row", "vertices", "surface", "springs", "tets", "interior", "upload ms", "paths ms", "path samples",
    "rig MB", "peak RSS MB", "linear ms", "paper CPU s/step", "note"};

std::string RowLine(const RowResult& r) {
  const std::vector<std::string> cells = {
      r.name,
      Cell(r.rig, [](const RigSummary& s) { return std::to_string(s.vertices); }),
      Cell(r.rig, [](const RigSummary& s) { return std::to_string(s.surface_vertices); }),
      Cell(r.rig, [](const RigSummary& s) { return std::to_string(s.springs); }),
      Cell(r.rig, [](const RigSummary& s) { return std::to_string(s.tetrahedra); }),
      Cell(r.rig, [](const RigSummary& s) { return s.interior; }),
      Cell(r.rig, [&](const RigSummary&) { return fmt::format("{:.0f}", r.build_ms); }),
      Cell(r.rig, [](const RigSummary& s) { return fmt::format("{:.0f}", s.path_ms); }),
      Cell(r.rig, [](const RigSummary& s) {
        return s.unconverged_path_samples > 0 ? fmt::format("{} ({} unconverged)", s.path_samples,
                                                            s.unconverged_path_samples)
                                              : std::to_string(s.path_samples);
      }),
      Cell(r.rig_mb, [](double mb) { return fmt::format("{:.0f}", mb); }),
      r.skipped ? "-" : Cell(r.peak_rss_mb, [](double mb) { return fmt::format("{:.0f}", mb); }),
      Cell(r.linear_ms, [](double ms) { return fmt::format("{:.3f}", ms); }),
      Cell(r.paper, [](const PaperFigure& p) {
        return fmt::format("{:.2f} s ({:.1f}k, {:.1f}k)", p.cpu_s_per_step, p.vertices_k, p.springs_k);
      }),
      Escape(r.note),
  };
  return fmt::format("| {} |", fmt::join(cells, " | "));
}

const std::vector<std::string> kMethodColumns = {
    "row", "method", "alone ms median", "alone p95", "alone max", "sweep ms/step", "speed-up", "Newton it",
    "CG it", "L-BFGS it", "fallbacks", "factorizations", "spring ms", "solve ms", "search ms", "factor ms",
    "accuracy", "start error", "minima", "jump", "alone = in order", "terminations"};

std::string MethodLine(const RowResult& r, const MethodResult& m) {
  const auto f1 = [](double v) { return fmt::format("{:.1f}", v); };
  const auto f2 = [](double v) { return fmt::format("{:.2f}", v); };
  std::optional<double> median, p95, max, sweep;
  if (m.alone) {
    const auto ms = m.alone->StepMs();
    median = Median(ms);
    p95 = Percentile(ms, 95.0);
    max = *std::max_element(ms.begin(), ms.end());
  }
  if (m.sweep) sweep = Median(m.sweep->StepMs());
  std::string speedup = "-";
  const MethodResult* base = r.baseline();
  if (median && base && base->alone && *median > 0.0) {
    speedup = fmt::format("{:.1f}x", Median(base->alone->StepMs()) / *median);
  }
  // Iterations and the split: from the alone pass (the sweep pass when there is none, as with --profile).
  const Pass* pass = m.alone ? &*m.alone : (m.sweep ? &*m.sweep : nullptr);
  const auto mean = [&](auto&& value) -> std::optional<double> {
    return pass ? std::optional<double>(pass->MeanOverSteps(value)) : std::nullopt;
  };
  const std::vector<std::string> cells = {
      r.name,
      m.config.name,
      Cell(median, f1),
      Cell(p95, f1),
      Cell(max, f1),
      Cell(sweep, f1),
      speedup,
      Cell(mean([](const SolveSummary& s) { return s.newton_iterations; }), f2),
      Cell(mean([](const SolveSummary& s) { return s.cg_iterations; }), f2),
      Cell(mean([](const SolveSummary& s) { return s.lbfgs_iterations; }), f2),
      Cell(mean([](const SolveSummary& s) { return s.newton_fallbacks; }), f2),
      Cell(mean([](const SolveSummary& s) { return s.factorizations; }), f2),
      Cell(mean([](const SolveSummary& s) { return s.spring_ms; }), f1),
      Cell(mean([](const SolveSummary& s) { return s.linear_solve_ms; }), f1),
      Cell(mean([](const SolveSummary& s) { return s.line_search_ms; }), f1),
      Cell(mean([](const SolveSummary& s) { return s.factorize_ms; }), f1),
      Cell(m.accuracy(), [](double a) { return fmt::format("{:.1e}", a); }),
      Cell(m.start_error(), [](double a) { return fmt::format("{:.1e}", a); }),
      m.alone ? fmt::format("{}/{}", m.alone->minima, m.alone->converged) : std::string("-"),
      m.alone ? fmt::format("{:.2f}", m.alone->continuity) : std::string("-"),
      Cell(m.same_alone_and_in_order(), [](const std::pair<int, int>& p) { return fmt::format("{}/{}", p.first, p.second); }),
      TerminationCell(m),
  };
  return fmt::format("| {} |", fmt::join(cells, " | "));
}

std::string GrowthText(const std::vector<RowResult>& rows, const Settings& settings) {
  const auto growth = CostGrowth(rows);
  if (!growth) return "Cost growth: fewer than two rows with distinct vertex counts measured.\n";
  std::vector<std::string> points;
  for (const auto& [name, p] : growth->points) {
    points.push_back(fmt::format("{} {} / {:.1f} ms", name, p.first, p.second));
  }
  return fmt::format(
      "Cost growth ({}, ms per frame alone, median, against simulated vertices; least-squares slope of the logs "
      "over {} rows): **exponent {:.2f}** ({}).\n",
      settings.methods.front(), growth->points.size(), growth->exponent, fmt::join(points, "; "));
}

std::string MarkdownReport(const Machine& machine, const Settings& settings, const std::vector<RowResult>& rows) {
  std::string md = "# springblend-bench\n\n";
  md += fmt::format("machine: nproc {}, {}, date {}, git {}\n\n", machine.nproc, machine.cpu, machine.date,
                    machine.git);
  md += fmt::format("options: follow_negative_curvature {}, mix start {}\n\n",
                    WithTolerances(SolveOptions{}).follow_negative_curvature ? "on" : "off",
                    WithTolerances(SolveOptions{}).scale_mix_start ? "scaled" : "summed");
  md += fmt::format(
      "Frames: the paper's sweep, {} frames from the rest shape (frame 0) to the target; figures over frames "
      "1..{}. Every frame is stateless (starts from the rig's prediction for its weights). **alone**: each frame "
      "by a fresh Solver (construction and first-use setup, such as the Laplacian's factor, included); "
      "**sweep**: one Solver solving the frames in order, median ms per step. Terminations count the alone "
      "and the sweep frames. Iterations and the time split "
      "(spring passes, linear solves, line search, factorizations) are means per frame of the alone pass. "
      "Speed-up: direct-newton (a fresh factorization and a direct solve per Newton iteration) alone median "
      "over the method's alone median. Accuracy: max over frames (alone and sweep) of the max vertex distance "
      "to a reference of the same frames (direct Newton, residual and step tolerance 1e-12){}, over the "
      "bounding-box diagonal. Start error: the same for the frames' starts (Solver::Start: the linear blend plus "
      "the target paths' corrections), before any iteration: how close the prediction alone is. Minima: alone "
      "frames whose true Hessian's Cholesky succeeds at the answer, of those converged; jump: the largest "
      "distance between consecutive alone frames over the linear blend's between them; alone = in order: frames "
      "whose answer alone and in the sweep (after every frame before it) is the same to the bit.{}\n\n",
      settings.steps, settings.steps - 1, settings.quick ? " (skipped: --quick)" : "",
      settings.profile ? " --profile: only the first method's sweep." : "");
  md += Header(kMethodColumns);
  for (const RowResult& row : rows) {
    for (const MethodResult& m : row.methods) md += MethodLine(row, m) + "\n";
  }
  md += "\n" + GrowthText(rows, settings) + "\n";
  md += "Per row: upload = Rig::Build wall time (paths ms: the targets' path corrections, part of it); rig MB = "
        "resident-set growth over the build (an estimate of the rig's memory); peak RSS = the process's "
        "resident high-water mark during the row (reset per row; rows run one after another in one process); "
        "linear = the linear blendshape, median ms per frame; paper: 2.66 GHz Core 2 Quad, PARDISO, s/step "
        "(vertices, springs).\n\n";
  md += Header(kRowColumns);
  for (const RowResult& row : rows) md += RowLine(row) + "\n";
  md += "\nEach row's sweep ends at these weights (the rest shape takes 1 minus their sum):\n\n";
  for (const RowResult& row : rows) md += fmt::format("- {}: {}\n", row.name, row.sweep_end);
  return md;
}

// ---- JSON ------------------------------------------------------------------------------------------------

json RigJson(const RigSummary& s) {
  json by_kind;
  for (int k = 0; k < kSpringKindCount; ++k) by_kind[ToString(static_cast<SpringKind>(k))] = s.springs_by_kind[k];
  return {{"vertices", s.vertices},
          {"surface_vertices", s.surface_vertices},
          {"springs", s.springs},
          {"springs_by_kind", by_kind},
          {"tetrahedra", s.tetrahedra},
          {"interior", s.interior},
          {"interior_reason", s.interior_reason},
          {"interior_vertices", s.interior_vertices},
          {"anchor_vertices", s.anchor_vertices},
          {"boundary_mode", ToString(s.boundary_mode)},
          {"hessian_nonzeros", s.hessian_nonzeros},
          {"precompute_ms", s.precompute_ms},
          {"path_ms", s.path_ms},
          {"path_samples", s.path_samples},
          {"unconverged_path_samples", s.unconverged_path_samples},
          {"notes", s.notes}};
}

json SummaryJson(const SolveSummary& s) {
  return {{"termination", ToString(s.termination)},
          {"minimum", ToString(s.minimum)},
          {"certify_ms", s.certify_ms},
          {"message", s.message},
          {"newton_iterations", s.newton_iterations},
          {"cg_iterations", s.cg_iterations},
          {"lbfgs_iterations", s.lbfgs_iterations},
          {"newton_fallbacks", s.newton_fallbacks},
          {"factorizations", s.factorizations},
          {"projected_factorizations", s.projected_factorizations},
          {"shifted_factorizations", s.shifted_factorizations},
          {"line_search_halvings", s.line_search_halvings},
          {"initial_residual", s.initial_residual},
          {"residual", s.residual},
          {"last_step", s.last_step},
          {"energy", s.energy},
          {"inverted_tetrahedra", s.inverted_tetrahedra},
          {"solve_ms", s.solve_ms},
          {"spring_ms", s.spring_ms},
          {"linear_solve_ms", s.linear_solve_ms},
          {"line_search_ms", s.line_search_ms},
          {"factorize_ms", s.factorize_ms}};
}

json PassJson(const Pass& pass) {
  const auto ms = pass.StepMs();
  json terminations = json::object();
  for (const auto& [termination, count] : pass.Terminations()) terminations[ToString(termination)] = count;
  json frames = json::array();
  for (size_t i = 0; i < pass.summaries.size(); ++i) {
    json frame = SummaryJson(pass.summaries[i]);
    frame["frame"] = pass.frame[i];
    frame["ms"] = pass.ms[i];
    frames.push_back(frame);
  }
  return {{"median_ms", Median(ms)},
          {"p95_ms", Percentile(ms, 95.0)},
          {"max_ms", ms.empty() ? 0.0 : *std::max_element(ms.begin(), ms.end())},
          {"accuracy", pass.has_accuracy ? json(pass.accuracy) : json(nullptr)},
          {"certified_minima", pass.minima},
          {"converged", pass.converged},
          {"continuity", pass.continuity},
          {"terminations", terminations},
          {"frames", frames}};
}

template <typename T, typename ToJson>
json OrNull(const std::optional<T>& value, ToJson&& to_json) {
  return value ? to_json(*value) : json(nullptr);
}

json RowJson(const RowResult& r) {
  const auto identity = [](double x) { return json(x); };
  json methods = json::array();
  const MethodResult* base = r.baseline();
  for (const MethodResult& m : r.methods) {
    json speedup = nullptr;
    if (m.alone && base && base->alone) speedup = Median(base->alone->StepMs()) / Median(m.alone->StepMs());
    methods.push_back({{"method", m.config.name},
                       {"baseline", m.config.baseline},
                       {"reuse_factorization", m.config.options.reuse_factorization},
                       {"residual_tolerance", m.config.options.residual_tolerance},
                       {"step_tolerance", m.config.options.step_tolerance},
                       {"alone", OrNull(m.alone, PassJson)},
                       {"sweep", OrNull(m.sweep, PassJson)},
                       {"accuracy", OrNull(m.accuracy(), identity)},
                       {"start_error", OrNull(m.start_error(), identity)},
                       {"alone_equals_in_order", OrNull(m.same_alone_and_in_order(),
                                                        [](const std::pair<int, int>& p) {
                                                          return json{{"same", p.first}, {"compared", p.second}};
                                                        })},
                       {"speedup_over_baseline", speedup}});
  }
  return {{"name", r.name},
          {"skipped", r.skipped},
          {"failed", r.failed},
          {"note", r.note},
          {"rig", OrNull(r.rig, RigJson)},
          {"build_ms", r.rig ? json(r.build_ms) : json(nullptr)},
          {"rig_mb", OrNull(r.rig_mb, identity)},
          {"peak_rss_mb", OrNull(r.peak_rss_mb, identity)},
          {"peak_rss_is_row", r.peak_is_row},
          {"ru_maxrss_mb", r.max_rss_mb},
          {"reference", OrNull(r.reference, PassJson)},
          {"methods", methods},
          {"linear_ms", OrNull(r.linear_ms, identity)},
          {"paper", OrNull(r.paper, [](const PaperFigure& p) {
             return json{{"cpu_s_per_step", p.cpu_s_per_step},
                         {"vertices_k", p.vertices_k},
                         {"springs_k", p.springs_k}};
           })}};
}

json JsonReport(const Machine& machine, const Settings& settings, const std::vector<RowResult>& rows) {
  json report = {{"machine",
                  {{"nproc", machine.nproc}, {"cpu", machine.cpu}, {"date", machine.date}, {"git", machine.git}}},
                 {"steps", settings.steps},
                 {"quick", settings.quick},
                 {"profile", settings.profile},
                 {"methods", settings.methods},
                 {"rows", json::array()}};
  for (const RowResult& row : rows) report["rows"].push_back(RowJson(row));
  if (const auto growth = CostGrowth(rows)) {
    json points = json::array();
    for (const auto& [name, p] : growth->points) {
      points.push_back({{"row", name}, {"vertices", p.first}, {"ms", p.second}});
    }
    report["cost_growth"] = {{"method", settings.methods.front()}, {"exponent", growth->exponent}, {"points", points}};
  }
  return report;
}

// ---- Plot ------------------------------------------------------------------------------------------------

// ms per frame against the frame, first method, frames solved alone (the sweep's ms with --profile). Writes
// the data and the gnuplot script (kept so the plot can be redrawn elsewhere) and runs gnuplot when it is
// installed. The plot is a convenience: nothing here fails the run.
void PlotMsPerStep(const std::vector<RowResult>& rows, const Settings& settings) {
  const fs::path& out = settings.out;
  std::ofstream data(out / "ms_per_step.dat");
  std::vector<std::string> plots;
  int steps = 1;
  for (const RowResult& row : rows) {
    if (row.methods.empty()) continue;
    const MethodResult& m = row.methods.front();
    const Pass* pass = m.alone ? &*m.alone : (m.sweep ? &*m.sweep : nullptr);
    if (pass == nullptr) continue;
    // gnuplot's `index` counts blocks separated by two blank lines.
    data << "# " << row.name << "\n";
    for (size_t i = 0; i < pass->ms.size(); ++i) {
      if (pass->frame[i] == 0) continue;
      steps = std::max(steps, pass->frame[i]);
      data << pass->frame[i] << " " << pass->ms[i] << "\n";
    }
    data << "\n\n";
    plots.push_back(fmt::format("'ms_per_step.dat' index {} using 1:2 with linespoints title '{}'", plots.size(),
                                row.name));
  }
  data.close();
  if (plots.empty()) {
    std::cerr << "plot: no measured row, nothing to draw\n";
    return;
  }
  std::ofstream script(out / "ms_per_step.gp");
  script << "if (strstrt(GPVAL_TERMINALS, 'pngcairo') > 0) {\n"
            "  set terminal pngcairo size 800,450\n"
            "} else {\n"
            "  set terminal png size 800,450\n"
            "}\n"
            "set output 'ms_per_step.png'\n"
         << fmt::format("set title 'springblend: ms per frame ({}, each frame solved alone)'\n",
                        settings.profile ? settings.methods.front() + " sweep" : settings.methods.front())
         << "set xlabel 'frame (alpha = frame / (steps - 1))'\n"
            "set ylabel 'ms (log scale)'\n"
            "set logscale y\n"
            "set grid\n"
            "set key outside right noenhanced\n"
         << fmt::format("set xtics {}\n", std::max(1, steps / 12))  // whole frames, about a dozen
         << "plot " << fmt::format("{}", fmt::join(plots, ", \\\n     ")) << "\n";
  script.close();
  if (std::system("command -v gnuplot >/dev/null 2>&1") != 0) {
    std::cerr << "plot: gnuplot not found, skipped (wrote " << (out / "ms_per_step.gp").string() << ")\n";
    return;
  }
  const std::string command = fmt::format("cd '{}' && gnuplot ms_per_step.gp", out.string());
  if (std::system(command.c_str()) == 0) {
    std::cerr << "plot: " << (out / "ms_per_step.png").string() << "\n";
  } else {
    std::cerr << "plot: gnuplot failed on " << (out / "ms_per_step.gp").string() << "\n";
  }
}

// ---- Driver ----------------------------------------------------------------------------------------------

void WriteReports(const Machine& machine, const Settings& settings, const std::vector<RowResult>& rows) {
  std::ofstream(settings.out / "bench.md") << MarkdownReport(machine, settings, rows);
  std::ofstream(settings.out / "bench.json") << JsonReport(machine, settings, rows).dump(2) << "\n";
}

std::vector<RowSpec> SelectRows(const Settings& settings) {
  std::vector<RowSpec> all = AllRows(settings.repo, settings.shared);
  if (settings.rows.empty()) return all;
  std::vector<RowSpec> selected;
  for (const std::string& name : settings.rows) {
    const auto it = std::find_if(all.begin(), all.end(), [&](const RowSpec& row) { return row.name == name; });
    if (it == all.end()) {
      std::vector<std::string> names;
      for (const RowSpec& row : all) names.push_back(row.name);
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("unknown row '{}' (rows: {})", name, fmt::join(names, ", ")));
    }
    selected.push_back(*it);
  }
  return selected;
}

// Exit status: 0 when every selected row was measured and every frame of every method converged (or the row
// was skipped for lack of files), 1 when a row failed or a frame did not converge, 2 for bad options.
int Run(const Settings& settings) {
  const std::vector<RowSpec> specs = SelectRows(settings);
  for (const std::string& method : settings.methods) SolveMethodFromString(method);  // bad names fail first
  std::error_code ec;
  fs::create_directories(settings.out, ec);
  if (ec || !fs::is_directory(settings.out)) {
    throw Error(ErrorCode::kInvalidInput, "cannot create the output directory " + settings.out.string());
  }
  const Machine machine = DescribeMachine(settings.repo);
  std::vector<RowResult> rows;
  for (const RowSpec& spec : specs) {
    // Reports are written after every pass and every row, so a long run that is stopped keeps what it measured.
    rows.emplace_back();
    RunRow(spec, settings, rows.back(), [&] { WriteReports(machine, settings, rows); });
    WriteReports(machine, settings, rows);
  }
  PlotMsPerStep(rows, settings);
  std::cout << MarkdownReport(machine, settings, rows);
  const bool ok = std::all_of(rows.begin(), rows.end(), [](const RowResult& row) { return row.ok(); });
  return ok ? 0 : 1;
}

int Main(int argc, char** argv) {
  Settings settings;
  CLI::App app{"springblend-bench: per row and per solve method, the paper's sweep's frames solved alone and in "
               "order, against direct Newton and a tightly converged reference"};
  app.add_option("--rows", settings.rows,
                 "comma-separated subset of: cylinder, cube, cheburashka, face, face-mix, horse, cat, face-random, "
                 "horse-random, cat-random (three targets each, drawn by a generator seeded with the row's name)")
      ->delimiter(',');
  CLI::Option* steps = app.add_option("--steps", settings.steps, "frames per sweep, including frame 0 (default 36)")
                           ->check(CLI::Range(2, 100000));
  app.add_flag("--quick", settings.quick, "6 frames (unless --steps is given) and no reference");
  app.add_flag("--profile", settings.profile,
               "run only the first method's sweep (no alone pass, baseline or reference), e.g. under perf record");
  app.add_option("--repo", settings.repo, "the springblend source tree (for tests/data and git describe)");
  app.add_option("--shared", settings.shared, "the shared meshes (default: <repo>/../shared/meshes)");
  app.add_option("--out", settings.out, "output directory for bench.md, bench.json and the plot");
  app.add_option("--method", settings.methods,
                 "comma-separated solve methods to measure side by side (newton, newton-laplacian, lbfgs; default "
                 "all three); the first is the plot's and the growth exponent's")
      ->delimiter(',');
  app.add_option("--residual-tolerance", g_residual_tolerance, "override SolveOptions::residual_tolerance");
  app.add_option("--step-tolerance", g_step_tolerance, "override SolveOptions::step_tolerance");
  std::string negative_curvature;
  app.add_option("--negative-curvature", negative_curvature,
                 "on|off: override SolveOptions::follow_negative_curvature (escaping saddles along the negative "
                 "curvature the conjugate gradients meet) in every configuration")
      ->check(CLI::IsMember({"on", "off"}));
  std::string mix_start;
  app.add_option("--mix-start", mix_start,
                 "scaled|summed: override SolveOptions::scale_mix_start (a mix frame's start at the lowest energy on "
                 "the ray through its targets' summed path corrections, or the full sum) in every configuration")
      ->check(CLI::IsMember({"scaled", "summed"}));
  std::string mix;
  app.add_option("--mix", mix,
                 "superposed|rest-lengths: override SolveOptions::mix (how a frame that moves several targets combines "
                 "them) in every configuration")
      ->check(CLI::IsMember({"superposed", "rest-lengths"}));
  app.add_option("--precomputed", g_precomputed_dir,
                 "directory keeping each row's target paths between runs (a later run loads them instead of solving "
                 "them; its upload column then measures a restart)");
  std::string linear_solver = ToString(g_linear_solver);
  app.add_option("--linear-solver", linear_solver, "sparse Cholesky backend: cholmod, cholmod-double, cholmod-library (CHOLMOD's own factorization), mumps or eigen")
      ->check(CLI::IsMember({"cholmod", "cholmod-double", "cholmod-library", "mumps", "eigen"}));
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
  }
  g_linear_solver = LinearSolverTypeFromString(linear_solver);
  if (!negative_curvature.empty()) g_follow_negative_curvature = negative_curvature == "on";
  if (!mix_start.empty()) g_scale_mix_start = mix_start == "scaled";
  if (!mix.empty()) g_mix = MixModelFromString(mix);
  if (settings.quick && steps->count() == 0) settings.steps = 6;
  if (settings.shared.empty()) settings.shared = settings.repo / ".." / "shared" / "meshes";
  if (settings.methods.empty()) {
    std::cerr << "springblend-bench: --method needs at least one method\n";
    return 2;
  }
  try {
    return Run(settings);
  } catch (const std::exception& e) {
    std::cerr << "springblend-bench: error: " << e.what() << "\n";
    return 2;
  }
}

}  // namespace
}  // namespace springblend::bench

int main(int argc, char** argv) {
  springblend::ConfigureNumericalThreads(argv);
  return springblend::bench::Main(argc, argv);
}
