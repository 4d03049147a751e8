// springblend-take-bench: a face driven by a captured performance, as a user drives one. The shared ICT face
// (../shared/meshes/face6706) with every expression it has, uploaded with the default options, driven by a Live
// Link Face take (../shared/performances/alex_rom_4.csv: ARKit's 52 shapes per frame), each frame solved alone
// with each mixing model asked for (SolveOptions::mix) and against the linear blend. Per model:
//   - ms per frame (median, p95, max; the certificate's factorization not counted), Newton iterations;
//   - pops: steps between consecutive frames whose largest vertex move exceeds twice the linear blend's and 1e-3
//     of the diagonal (the worst ratio too);
//   - the distance from the linear blend (largest vertex distance over the diagonal: median, p95, max);
//   - frames converged and certified local minima (SolveOptions::certify_minimum).
// The rig's build (upload) time is measured once; --cache FILE keeps its paths between runs (a build of all 55
// expressions takes minutes on two cores). The worst frame of each model (farthest from the linear blend) is
// written as OBJ beside its linear blend. Skips with a line when the face or the take is absent.
#include <fmt/format.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <vector>

#include <sys/resource.h>

#include "take.h"
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

double Percentile(std::vector<double> v, double p) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  const auto rank = static_cast<size_t>(std::ceil(p / 100.0 * static_cast<double>(v.size())));
  return v[std::clamp<size_t>(rank, 1, v.size()) - 1];
}

double MaxDistance(const Points& a, const Points& b) { return std::sqrt((a - b).rowwise().squaredNorm().maxCoeff()); }

struct Settings {
  fs::path face;
  fs::path take;
  fs::path out = "bench-results";
  fs::path cache;
  int first = 0;
  int count = 120;
  int stride = 1;
  std::vector<std::string> models = {"superposed", "rest-lengths"};
  bool certify = true;
  bool verbose = false;
  bool per_target = false;
  RigOptions rig;
  std::string method = "newton";
  double local_finish_share = SolveOptions{}.local_finish_share;
  bool negative_curvature = SolveOptions{}.follow_negative_curvature;
  bool projected = false;
  std::vector<std::string> targets;  // the expressions uploaded (all when empty)
};

int Run(const Settings& settings) {
  if (!fs::is_regular_file(settings.face / "generic_neutral_mesh.obj") || !fs::is_regular_file(settings.take)) {
    fmt::print("take bench: skipped ({} or {} absent)\n", (settings.face / "generic_neutral_mesh.obj").string(),
               settings.take.string());
    return 0;
  }
  const TriangleMesh rest = LoadMesh((settings.face / "generic_neutral_mesh.obj").string());
  std::vector<TargetSpec> specs;
  std::vector<fs::path> files;
  for (const auto& entry : fs::directory_iterator(settings.face)) {
    if (entry.path().extension() == ".obj" && entry.path().filename() != "generic_neutral_mesh.obj") {
      files.push_back(entry.path());
    }
  }
  std::sort(files.begin(), files.end());
  for (const auto& f : files) {
    if (!settings.targets.empty() &&
        std::find(settings.targets.begin(), settings.targets.end(), f.stem().string()) == settings.targets.end()) {
      continue;
    }
    TargetSpec t;
    t.mesh = LoadMesh(f.string());
    t.name = f.stem().string();
    specs.push_back(std::move(t));
  }
  const cli::Take take = cli::ReadTake(settings.take.string());
  RigBuildControl control;
  std::string cached;
  if (!settings.cache.empty() && fs::is_regular_file(settings.cache)) {
    control.precomputed_file = PrecomputedLocation{settings.cache.string()};
  }
  const auto build_start = Clock::now();
  const auto rig = Rig::Build(rest, specs, settings.rig, control);
  const double build_ms = MsSince(build_start);
  const RigSummary& summary = rig->summary();
  if (!settings.cache.empty() && !summary.paths_loaded) {
    fs::create_directories(settings.cache.parent_path().empty() ? fs::path(".") : settings.cache.parent_path());
    std::ofstream(settings.cache, std::ios::binary) << rig->SavePrecomputed();
  }
  fmt::print("face: {} targets, {} vertices ({} simulated), {} springs, {}; build {:.1f} s{} ({} uncertified "
             "path intervals, {} static, {} rim)\n",
             rig->num_targets(), summary.surface_vertices, summary.vertices, summary.springs, summary.interior,
             build_ms / 1000.0, summary.paths_loaded ? " with its paths loaded" : "", summary.uncertified_path_intervals,
             summary.static_vertices, summary.rim_vertices);
  if (!summary.paths_loaded) {
    rusage usage{};
    getrusage(RUSAGE_SELF, &usage);
    const double cpu = static_cast<double>(usage.ru_utime.tv_sec + usage.ru_stime.tv_sec) +
                       1e-6 * static_cast<double>(usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
    int samples = 0, solves = 0, checks = 0;
    for (const auto& p : summary.paths) {
      samples += p.samples, solves += p.solves, checks += p.checks;
      if (settings.verbose) {
        fmt::print("  path {:>18}: {} samples, {} solves ({} checks, {} local), {} uncertified, {:.1f} s\n", p.target,
                   p.samples, p.solves, p.checks, p.local_checks, p.uncertified, p.ms / 1000.0);
      }
    }
    fmt::print("paths: {} samples, {} solves ({} checks), process CPU {:.1f} s\n", samples, solves, checks, cpu);
  }
  // The tracked rows (lost ones skipped), matched to the face's targets by name as the CLI matches them.
  const std::vector<std::vector<double>> all =
      cli::MatchTake(take, rig->target_names(), nullptr, cli::LostRows::kSkip).weights;
  std::vector<std::vector<double>> frames;
  for (int i = settings.first; i < static_cast<int>(all.size()) && static_cast<int>(frames.size()) < settings.count;
       i += settings.stride) {
    frames.push_back(all[i]);
  }
  std::vector<double> active;
  for (const auto& w : frames) active.push_back(static_cast<double>(std::count_if(w.begin(), w.end(), [](double x) { return x > 0.05; })));
  fmt::print("take: {} rows, frames {}..{} step {} ({} frames), expressions above 0.05: median {:.0f}, max {:.0f}\n",
             all.size(), settings.first, settings.first + settings.stride * (static_cast<int>(frames.size()) - 1),
             settings.stride, frames.size(), Percentile(active, 50), Percentile(active, 100));
  const double diagonal = summary.bounding_box_diagonal;
  SolveOptions linear_options;
  linear_options.linear = true;
  Solver linear_solver(rig, linear_options);
  std::vector<Points> linear(frames.size());
  for (size_t i = 0; i < frames.size(); ++i) {
    Frame frame;
    frame.weights = frames[i];
    linear_solver.Solve(frame, &linear[i]);
  }
  fs::create_directories(settings.out);
  if (settings.per_target) {
    // Each target alone at its weight in the first frame: its path's start and answer.
    SolveOptions options;
    Solver solver(rig, options);
    for (int t = 0; t < rig->num_targets(); ++t) {
      if (frames[0][t] == 0.0) continue;
      Frame frame;
      frame.weights.assign(rig->num_targets(), 0.0);
      frame.weights[t] = frames[0][t];
      Points x, lin;
      const SolveSummary s = solver.Solve(frame, &x);
      linear_solver.Solve(frame, &lin);
      const Points start = solver.Start(frame.weights).topRows(rig->num_surface_vertices());
      WriteObj((settings.out / fmt::format("alone-{}.obj", rig->target_names()[t])).string(), x, rest.faces);
      WriteObj((settings.out / fmt::format("alone-{}-linear.obj", rig->target_names()[t])).string(), lin, rest.faces);
      fmt::print("  {:>18} at {:.3f}: start from linear {:.3f} %, answer from start {:.4f} %, initial residual {:.1e}, "
                 "{} Newton, {:.0f} ms, {}\n",
                 rig->target_names()[t], frame.weights[t], 100 * MaxDistance(start, lin) / diagonal,
                 100 * MaxDistance(x, start) / diagonal, s.initial_residual, s.newton_iterations, s.solve_ms,
                 ToString(s.finish));
    }
  }
  json report;
  report["build_ms"] = build_ms;
  report["frames"] = frames.size();
  fs::create_directories(settings.out);
  fmt::print("\n| model | converged | minima | ms median | ms p95 | ms max | Newton median | Newton max | pops | worst "
             "step ratio | from linear median | p95 | max |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n");
  int first_worst = -1;
  for (const std::string& model : settings.models) {
    SolveOptions options;
    options.mix = MixModelFromString(model);
    options.method = SolveMethodFromString(settings.method);
    options.local_finish_share = settings.local_finish_share;
    options.follow_negative_curvature = settings.negative_curvature;
    if (settings.projected) options.hessian = HessianMode::kProjected;
    options.certify_minimum = settings.certify;
    Solver solver(rig, options);
    std::vector<Points> solved(frames.size());
    std::vector<double> ms, newton, distance;
    int converged = 0, minima = 0, pops = 0;
    double worst_ratio = 0.0;
    size_t worst = 0;
    for (size_t i = 0; i < frames.size(); ++i) {
      Frame frame;
      frame.weights = frames[i];
      const SolveSummary s = solver.Solve(frame, &solved[i]);
      if (settings.verbose) {
        const Points start = solver.Start(frame.weights).topRows(rig->num_surface_vertices());
        fmt::print("  {} frame {}: start from linear {:.3f} %, answer from start {:.3f} %, from linear {:.3f} %, "
                   "strain share {:.3f}, initial residual {:.2e}, {} Newton, {:.0f} ms (mix {:.0f}, springs {:.0f}, linear solves {:.0f}, "
                   "factorizations {} in {:.0f}, projected {}, shifted {}, CG {}, halvings {}), {}\n",
                   model, settings.first + settings.stride * static_cast<int>(i),
                   100 * MaxDistance(start, linear[i]) / diagonal, 100 * MaxDistance(solved[i], start) / diagonal,
                   100 * MaxDistance(solved[i], linear[i]) / diagonal, s.mix_strain_share, s.initial_residual,
                   s.newton_iterations,
                   s.solve_ms, s.mix_ms, s.spring_ms, s.linear_solve_ms, s.factorizations, s.factorize_ms,
                   s.projected_factorizations, s.shifted_factorizations, s.cg_iterations, s.line_search_halvings,
                   ToString(s.finish));
      }
      ms.push_back(s.solve_ms - s.certify_ms);
      newton.push_back(s.newton_iterations);
      converged += s.converged();
      minima += s.minimum == MinimumCheck::kMinimum;
      distance.push_back(MaxDistance(solved[i], linear[i]) / diagonal);
      if (distance.back() > distance[worst]) worst = i;
      if (i > 0) {
        const double step = MaxDistance(solved[i], solved[i - 1]) / diagonal;
        const double linear_step = MaxDistance(linear[i], linear[i - 1]) / diagonal;
        const double ratio = step / std::max(linear_step, 1e-12);
        if (step > 1e-3) worst_ratio = std::max(worst_ratio, ratio);
        if (step > 1e-3 && ratio > 2.0) ++pops;
      }
    }
    fmt::print("| {} | {}/{} | {} | {:.1f} | {:.1f} | {:.1f} | {:.0f} | {:.0f} | {} | {:.2f} | {:.3f} % | {:.3f} % | {:.3f} % |\n",
               model, converged, frames.size(), minima, Percentile(ms, 50), Percentile(ms, 95), Percentile(ms, 100),
               Percentile(newton, 50), Percentile(newton, 100), pops, worst_ratio, 100 * Percentile(distance, 50),
               100 * Percentile(distance, 95), 100 * Percentile(distance, 100));
    report[model] = {{"converged", converged}, {"minima", minima}, {"ms_median", Percentile(ms, 50)},
                     {"ms_p95", Percentile(ms, 95)}, {"ms_max", Percentile(ms, 100)},
                     {"newton_median", Percentile(newton, 50)}, {"newton_max", Percentile(newton, 100)},
                     {"pops", pops}, {"worst_step_ratio", worst_ratio},
                     {"distance_median", Percentile(distance, 50)}, {"distance_p95", Percentile(distance, 95)},
                     {"distance_max", Percentile(distance, 100)}, {"worst_frame", settings.first + settings.stride * static_cast<int>(worst)}};
    WriteObj((settings.out / fmt::format("take-{}-worst.obj", model)).string(), solved[worst], rest.faces);
    WriteObj((settings.out / fmt::format("take-{}-worst-linear.obj", model)).string(), linear[worst], rest.faces);
    // Every model's answer at the first model's worst frame, for a picture of one frame (docs/render_take_figure.py).
    if (first_worst < 0) first_worst = static_cast<int>(worst);
    const int at = settings.first + settings.stride * first_worst;
    WriteObj((settings.out / fmt::format("take-{}-at-{}.obj", model, at)).string(), solved[first_worst], rest.faces);
    if (&model == &settings.models.front()) {
      WriteObj((settings.out / fmt::format("take-linear-at-{}.obj", at)).string(), linear[first_worst], rest.faces);
    }
  }
  std::ofstream(settings.out / "take.json") << report.dump(2) << "\n";
  return 0;
}

}  // namespace
}  // namespace springblend::bench

int main(int argc, char** argv) {
  // One thread per numerical library, as the server runs: the paths build in parallel (without it, OpenBLAS's
  // threads spin against the paths' own and the upload measured 1.6x slower).
  springblend::ConfigureNumericalThreads(argv);
  namespace fs = std::filesystem;
  springblend::bench::Settings settings;
  const fs::path shared = fs::path(SPRINGBLEND_SOURCE_DIR) / ".." / "shared";
  settings.face = shared / "meshes" / "face6706";
  settings.take = shared / "performances" / "alex_rom_4.csv";
  CLI::App app{"springblend-take-bench: a face driven by a captured take, per mixing model"};
  app.add_option("--face", settings.face, "the face's directory (generic_neutral_mesh.obj and one OBJ per expression)");
  app.add_option("--take", settings.take, "a Live Link Face CSV");
  app.add_option("--out", settings.out, "where take.json and the worst frames go");
  app.add_option("--cache", settings.cache, "keep the rig's paths in this file between runs (built when absent)");
  app.add_option("--first", settings.first, "the take's first frame solved");
  app.add_option("--count", settings.count, "frames solved");
  app.add_option("--stride", settings.stride, "every how many of the take's frames");
  app.add_option("--models", settings.models, "mixing models (superposed, rest-lengths)")->delimiter(',');
  app.add_flag("!--no-certify", settings.certify, "skip the local-minimum certificate");
  app.add_flag("--hold-outer-rim,!--no-hold-outer-rim", settings.rig.hold_outer_rim,
               "hold the open surface's outer rim on the linear blend (RigOptions::hold_outer_rim)");
  app.add_option("--local-finish-share", settings.local_finish_share,
                 "largest share of the vertices a local finish may solve (SolveOptions::local_finish_share)");
  app.add_flag("!--no-negative-curvature", settings.negative_curvature,
               "without SolveOptions::follow_negative_curvature");
  app.add_flag("--projected", settings.projected, "the projected Hessian always (HessianMode::kProjected)");
  app.add_option("--targets", settings.targets, "only these expressions (file stems), for build-time experiments")
      ->delimiter(',');
  app.add_option("--path-intervals", settings.rig.path_intervals, "RigOptions::path_intervals");
  app.add_option("--path-extension", settings.rig.path_extension, "RigOptions::path_extension");
  app.add_option("--path-tolerance", settings.rig.path_tolerance, "RigOptions::path_tolerance");
  app.add_option("--path-max-samples", settings.rig.path_max_samples, "RigOptions::path_max_samples");
  app.add_option("--method", settings.method, "newton, newton-laplacian or lbfgs (SolveOptions::method)");
  app.add_flag("--per-target", settings.per_target, "each target of the first frame alone: its start and answer");
  app.add_flag("--verbose", settings.verbose, "a line per frame: its start's and answer's distances, residual, iterations");
  CLI11_PARSE(app, argc, argv);
  try {
    return springblend::bench::Run(settings);
  } catch (const std::exception& e) {
    std::cerr << "take bench: " << e.what() << "\n";
    return 1;
  }
}
