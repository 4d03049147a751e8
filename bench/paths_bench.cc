// springblend-paths-bench: what the rig's target paths buy. Per row (a rest mesh and its targets):
//   - the rig build, and per target its path's build time, samples, solves and certified midpoint error;
//   - the rig's memory with and without its paths (the rig's own estimate, and the resident-set growth);
//   - a restart: the rig built again with its paths left in the file they were saved to (as the server's cache
//     file), its resident-set growth, the path bytes it holds and leaves in the file, and its first frame;
//   - path frames: each target alone at --frames off-sample alphas over [-0.25, 1.25] (the in-between weights
//     and the extrapolated ends included when the rig has them), solved by the shipped options (a local finish
//     from the dense path, read from that file as the server does) and by the full solve from the same start
//     (the baseline of the same run, on the rig as built), with
//     ms (median, max), how each frame was finished and the share of vertices solved;
//   - accuracy: the largest distance of a path frame from the same frame solved to 1e-12 from the path's
//     start, over the bounding-box diagonal.
// Rows whose meshes are absent are skipped with a line. Prints a Markdown table and writes OUT/paths.md and
// OUT/paths.json.
#include <fmt/format.h>
#include <malloc.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <nlohmann/json.hpp>
#include <optional>
#include <sstream>
#include <string>
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

std::optional<double> ResidentMb() { return StatusMb("VmRSS"); }

struct RowSpec {
  std::string name;
  fs::path dir;
  std::string rest;
  std::vector<std::string> targets;
  // Besides them, this many targets made of two of them summed at 0.6 each (pairs in a fixed order): a stand-in
  // for a production face's count of expressions.
  int pairs = 0;
};

std::vector<RowSpec> AllRows(const fs::path& repo, const fs::path& shared) {
  const fs::path data = repo / "tests" / "data";
  return {
      {"cylinder", data / "cylinder", "cylinder.obj", {"poses-2_cylinder-1.obj"}},
      {"cube", data / "cube", "cube.obj", {"poses-1_cube-4.obj"}},
      {"cheburashka", data / "cheburashka", "cheburashka.obj", {"poses-1_cheburashka-1.obj"}},
      {"face", shared / "face6706", "generic_neutral_mesh.obj", {"jawOpen.obj"}},
      {"face-5",
       shared / "face6706",
       "generic_neutral_mesh.obj",
       {"jawOpen.obj", "mouthSmile_L.obj", "mouthSmile_R.obj", "eyeBlink_L.obj", "browInnerUp_L.obj"}},
      {"face-16",
       shared / "face6706",
       "generic_neutral_mesh.obj",
       {"browDown_L.obj", "browDown_R.obj", "browInnerUp_L.obj", "browInnerUp_R.obj", "cheekPuff_L.obj",
        "cheekPuff_R.obj", "eyeBlink_L.obj", "eyeBlink_R.obj", "jawOpen.obj", "mouthClose.obj", "mouthFunnel.obj",
        "mouthPucker.obj", "mouthSmile_L.obj", "mouthSmile_R.obj", "noseSneer_L.obj", "noseSneer_R.obj"}},
      // 52 expressions, as a production face has (ARKit's count): the 16 and 36 pairs of them (no such face is at
      // hand); a build of about ten minutes.
      {"face-52",
       shared / "face6706",
       "generic_neutral_mesh.obj",
       {"browDown_L.obj", "browDown_R.obj", "browInnerUp_L.obj", "browInnerUp_R.obj", "cheekPuff_L.obj",
        "cheekPuff_R.obj", "eyeBlink_L.obj", "eyeBlink_R.obj", "jawOpen.obj", "mouthClose.obj", "mouthFunnel.obj",
        "mouthPucker.obj", "mouthSmile_L.obj", "mouthSmile_R.obj", "noseSneer_L.obj", "noseSneer_R.obj"},
       36},
      {"horse", shared / "horse", "horse-reference.obj", {"horse-01.obj"}},
      {"cat", shared / "cat", "cat-reference.obj", {"cat-01.obj"}},
  };
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

double MaxDistance(const Points& a, const Points& b) {
  return std::sqrt((a - b).rowwise().squaredNorm().maxCoeff());
}

struct Settings {
  fs::path repo = SPRINGBLEND_SOURCE_DIR;
  fs::path shared;
  fs::path out = "bench-results";
  std::vector<std::string> rows = {"cylinder", "cube", "cheburashka", "face", "horse", "cat"};
  int frames = 17;
  int targets_measured = 2;  // frames are measured on the first this many targets of a row
  bool reference = true;
  bool span = true;  // SolveOptions::path_span_step for the path frames
  double local_finish_share = SolveOptions{}.local_finish_share;  // SolveOptions::local_finish_share
  bool spool = false;  // RigBuildControl::spool_directory (the output directory) for the builds
  RigOptions rig;  // the paths' options (--path-*)
};

// The row's targets, each named after its mesh (a pair: "<a>+<b>").
std::vector<TargetSpec> TargetsOf(const RowSpec& spec) {
  std::vector<TargetSpec> targets;
  for (const auto& t : spec.targets) {
    TargetSpec target;
    target.mesh = LoadMesh((spec.dir / t).string());
    target.name = target.mesh.name;
    targets.push_back(std::move(target));
  }
  const int n = static_cast<int>(spec.targets.size());
  if (spec.pairs > 0) {
    const TriangleMesh rest = LoadMesh((spec.dir / spec.rest).string());
    for (int k = 0; k < spec.pairs; ++k) {
      const int a = k % n, b = (a + 1 + k / n) % n;  // distinct pairs while pairs < n (n - 1) / 2
      TargetSpec target;
      target.mesh = rest;
      target.mesh.vertices = rest.vertices + 0.6 * (targets[a].mesh.vertices - rest.vertices) +
                             0.6 * (targets[b].mesh.vertices - rest.vertices);
      target.name = fmt::format("{}+{}", targets[a].name, targets[b].name);
      target.mesh.name = target.name;
      targets.push_back(std::move(target));
    }
  }
  return targets;
}

json RunRow(const RowSpec& spec, const Settings& settings) {
  json row;
  row["row"] = spec.name;
  TriangleMesh rest = LoadMesh((spec.dir / spec.rest).string());
  std::vector<TargetSpec> targets = TargetsOf(spec);
  malloc_trim(0);
  const auto before = ResidentMb();
  const bool peak_reset = ResetPeakRss();
  RigBuildControl build;
  if (settings.spool) {
    // As the server builds an upload: each target's path out of memory as soon as it is solved.
    fs::create_directories(settings.out);
    build.spool_directory = settings.out.string();
  }
  const auto build_start = Clock::now();
  const std::shared_ptr<const Rig> rig = Rig::Build(std::move(rest), std::move(targets), settings.rig, build);
  row["build_ms"] = MsSince(build_start);
  const auto peak = StatusMb("VmHWM");
  if (peak_reset && before && peak) row["build_peak_mb"] = std::max(0.0, *peak - *before);
  malloc_trim(0);
  const auto after = ResidentMb();
  if (before && after) row["rig_resident_mb"] = std::max(0.0, *after - *before);
  row["spooled"] = settings.spool;
  const RigSummary& s = rig->summary();
  row["vertices"] = s.vertices;
  row["targets"] = s.targets;
  row["path_ms"] = s.path_ms;
  row["path_mb"] = s.path_bytes / 1048576.0;
  row["rig_mb_without_paths"] = s.rig_bytes / 1048576.0;
  row["path_samples"] = s.path_samples;
  row["path_solves"] = s.path_solves;
  row["path_max_error"] = s.path_max_error;
  row["uncertified_intervals"] = s.uncertified_path_intervals;
  json per_target = json::array();
  for (const auto& p : s.paths) {
    per_target.push_back({{"target", p.target}, {"samples", p.samples}, {"solves", p.solves}, {"ms", p.ms},
                          {"max_error", p.max_error}, {"uncertified", p.uncertified}, {"checks", p.checks},
                          {"local_checks", p.local_checks}, {"uncertified_ranges", p.uncertified_ranges}});
  }
  row["paths"] = per_target;
  std::shared_ptr<const Rig> served = rig;
  fs::path saved_file;
  {
    // A restart: the same meshes built again with the saved paths, and its first frame.
    const std::string saved = rig->SavePrecomputed();
    TriangleMesh rest2 = LoadMesh((spec.dir / spec.rest).string());
    std::vector<TargetSpec> specs = TargetsOf(spec);
    // As the server restarts: the paths left in the file they were saved to, their samples read as frames need
    // them (RigBuildControl::precomputed_file), so the restarted rig holds only their metadata.
    saved_file = settings.out / (spec.name + ".precomputed");
    fs::create_directories(settings.out);
    std::ofstream(saved_file, std::ios::binary) << saved;
    RigBuildControl control;
    control.precomputed_file = PrecomputedLocation{saved_file.string()};
    malloc_trim(0);
    const auto reload_before = ResidentMb();
    const auto reload_start = Clock::now();
    const auto reloaded = Rig::Build(std::move(rest2), std::move(specs), settings.rig, control);
    row["reload_ms"] = MsSince(reload_start);
    malloc_trim(0);
    const auto reload_after = ResidentMb();
    if (reload_before && reload_after) row["reload_resident_mb"] = std::max(0.0, *reload_after - *reload_before);
    row["reload_paths_loaded"] = reloaded->summary().paths_loaded;
    Solver first(reloaded);
    Frame frame;
    frame.weights.assign(reloaded->num_targets(), 0.0);
    frame.weights[0] = 0.55;
    Points x;
    const SolveSummary summary = first.Solve(frame, &x);
    row["reload_first_frame_ms"] = summary.solve_ms;
    row["precomputed_mb"] = saved.size() / 1048576.0;
    row["reload_path_mb_held"] = reloaded->summary().path_bytes / 1048576.0;
    row["reload_path_mb_in_file"] = reloaded->summary().path_file_bytes / 1048576.0;
    served = reloaded;  // the path frames below read their samples from the file, as the server's do
    // Its two-thread solve's schedule, planned once per rig (about 0.1-0.2 s) on its first preconditioned solve:
    // the built rig planned it during its path build, so the restarted one plans it here, untimed, rather than in
    // the first path frame that falls back to a full solve.
    SolveOptions full_solve;
    full_solve.local_finish = false;
    full_solve.path_span_step = false;
    Solver(reloaded, full_solve).Solve(frame, &x);
  }

  const double diagonal = s.bounding_box_diagonal;
  SolveOptions shipped;
  shipped.path_span_step = settings.span;
  shipped.local_finish_share = settings.local_finish_share;
  SolveOptions full = shipped;
  full.local_finish = false;
  full.path_span_step = false;  // the baseline: Newton from the interpolant
  SolveOptions tight = full;
  tight.residual_tolerance = 1e-12;
  tight.step_tolerance = 1e-12;
  tight.max_iterations = 400;
  Solver path_solver(served, shipped), full_solver(rig, full), tight_solver(rig, tight);
  std::vector<double> path_ms, full_ms, accuracy, share, start_memory_ms, start_file_ms;
  std::vector<double> certified_ms, uncertified_ms;  // path frames where their path is certified, and elsewhere
  double certified_start_error = 0.0;
  int local = 0, frames = 0, converged = 0;
  json frame_rows = json::array();
  const int measured = std::min<int>(settings.targets_measured, rig->num_targets());
  for (int t = 0; t < measured; ++t) {
    for (int j = 0; j < settings.frames; ++j) {
      // Off-sample alphas spread over [-0.25, 1.25]: a golden-ratio sequence never meets the samples'
      // dyadic weights.
      const double u = 0.5 + 0.6180339887498949 * j;
      const double alpha = -0.25 + 1.5 * (u - std::floor(u));
      Frame frame;
      frame.weights.assign(rig->num_targets(), 0.0);
      frame.weights[t] = alpha;
      Points p, f, r, start;
      // The frame's start (the paths' interpolant) from samples held and from samples read from the file.
      for (int pass = 0; pass < 2; ++pass) {
        const auto clock = Clock::now();
        start = (pass == 0 ? full_solver : path_solver).Start(frame.weights);
        (pass == 0 ? start_memory_ms : start_file_ms).push_back(MsSince(clock));
      }
      // Whether the frame's weight lies where its target's path is certified.
      bool in_certified = true;
      for (const auto& summary_path : s.paths) {
        if (summary_path.target != rig->target_names()[t]) continue;
        for (const auto& [from, to] : summary_path.uncertified_ranges) in_certified &= !(alpha >= from && alpha <= to);
      }
      const SolveSummary ps = path_solver.Solve(frame, &p);
      const SolveSummary fs_ = full_solver.Solve(frame, &f);
      ++frames;
      converged += ps.converged() ? 1 : 0;
      local += ps.finish == Finish::kLocal ? 1 : 0;
      path_ms.push_back(ps.solve_ms);
      (in_certified ? certified_ms : uncertified_ms).push_back(ps.solve_ms);
      // How far the interpolant started from the answer: within a certified interval, about the certified
      // bound (checked at the interval's midpoint only).
      const double start_error = MaxDistance(start.topRows(p.rows()), p) / diagonal;
      if (in_certified) certified_start_error = std::max(certified_start_error, start_error);
      full_ms.push_back(fs_.solve_ms);
      share.push_back(ps.free_vertices > 0 ? static_cast<double>(ps.solved_vertices) / ps.free_vertices : 0.0);
      json fr = {{"target", t},          {"alpha", alpha},          {"ms", ps.solve_ms},
                 {"full_ms", fs_.solve_ms}, {"finish", ToString(ps.finish)}, {"solved", ps.solved_vertices},
                 {"free", ps.free_vertices}, {"termination", ToString(ps.termination)},
                 {"note", ps.local_finish_note}, {"newton", ps.newton_iterations},
                 {"span_vectors", ps.span_vectors}, {"certified", in_certified}, {"start_error", start_error}};
      if (settings.reference) {
        const SolveSummary rs = tight_solver.Solve(frame, &r);
        const double a = MaxDistance(p, r) / diagonal;
        accuracy.push_back(a);
        fr["accuracy"] = a;
        fr["reference_converged"] = rs.converged();
        fr["full_vs_reference"] = MaxDistance(f, r) / diagonal;
      }
      frame_rows.push_back(fr);
      std::cerr << fr.dump() << "\n";
    }
  }
  served.reset();
  fs::remove(saved_file);
  row["frames"] = frames;
  row["frames_converged"] = converged;
  row["frames_local"] = local;
  row["start_ms_median_memory"] = Median(start_memory_ms);
  row["start_ms_median_file"] = Median(start_file_ms);
  row["path_frame_ms_median"] = Median(path_ms);
  row["path_frame_ms_max"] = path_ms.empty() ? 0.0 : *std::max_element(path_ms.begin(), path_ms.end());
  row["certified_frames"] = static_cast<int>(certified_ms.size());
  row["certified_frame_ms_median"] = Median(certified_ms);
  row["certified_frame_ms_max"] =
      certified_ms.empty() ? 0.0 : *std::max_element(certified_ms.begin(), certified_ms.end());
  row["certified_start_error_max"] = certified_start_error;
  row["uncertified_frame_ms_median"] = Median(uncertified_ms);
  row["uncertified_frame_ms_max"] =
      uncertified_ms.empty() ? 0.0 : *std::max_element(uncertified_ms.begin(), uncertified_ms.end());
  row["full_frame_ms_median"] = Median(full_ms);
  row["full_frame_ms_max"] = full_ms.empty() ? 0.0 : *std::max_element(full_ms.begin(), full_ms.end());
  row["speedup_median"] = Median(path_ms) > 0 ? Median(full_ms) / Median(path_ms) : 0.0;
  row["share_median"] = Median(share);
  row["accuracy_max"] = accuracy.empty() ? 0.0 : *std::max_element(accuracy.begin(), accuracy.end());
  row["frame_list"] = frame_rows;
  return row;
}

std::string Table(const json& rows) {
  std::ostringstream out;
  out << "| row | vertices | targets | build s | path ms/target | samples/target | max certified error | "
         "uncertified | path MB | rig MB w/o paths | resident MB | build peak MB | restart: resident MB / path MB held / in file | restart: build + first frame s | start ms, paths held / in file | path frame ms "
         "median / max | certified: frames, ms median / max, start error max | elsewhere: ms median / max | full solve ms median / max | speed-up | local | share solved | accuracy |\n";
  out << "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | "
         "---: | ---: | ---: | ---: | ---: |\n";
  for (const json& r : rows) {
    if (r.contains("skipped")) {
      out << fmt::format("| {} | skipped: {} |\n", r["row"].get<std::string>(), r["skipped"].get<std::string>());
      continue;
    }
    const int with_paths = std::max<int>(1, static_cast<int>(r["paths"].size()));
    double path_ms_sum = 0.0;
    for (const auto& p : r["paths"]) path_ms_sum += p["ms"].get<double>();
    out << fmt::format(
        "| {} | {} | {} | {:.1f} | {:.0f} | {:.1f} | {:.1e} | {} | {:.1f} | {:.1f} | {:.0f} | {:.0f}{} | {:.0f} / {:.2f} / {:.1f} | {:.2f} | {:.2f} / {:.2f} | {:.1f} / {:.1f} | {} / {}, {:.1f} / {:.1f}, {:.1e} | {:.1f} / {:.1f} | "
        "{:.0f} / {:.0f} | {:.0f}x | {}/{} | {:.3f} | {:.1e} |\n",
        r["row"].get<std::string>(), r["vertices"].get<int>(), r["targets"].get<int>(),
        r["build_ms"].get<double>() / 1000.0, path_ms_sum / with_paths,
        static_cast<double>(r["path_samples"].get<int>()) / with_paths, r["path_max_error"].get<double>(),
        r["uncertified_intervals"].get<int>(), r["path_mb"].get<double>(), r["rig_mb_without_paths"].get<double>(),
        r.value("rig_resident_mb", 0.0), r.value("build_peak_mb", 0.0), r.value("spooled", false) ? " (spool)" : "",
        r.value("reload_resident_mb", 0.0), r.value("reload_path_mb_held", 0.0),
        r.value("reload_path_mb_in_file", 0.0),
        (r.value("reload_ms", 0.0) + r.value("reload_first_frame_ms", 0.0)) / 1000.0,
        r.value("start_ms_median_memory", 0.0), r.value("start_ms_median_file", 0.0), r["path_frame_ms_median"].get<double>(),
        r["path_frame_ms_max"].get<double>(), r.value("certified_frames", 0), r["frames"].get<int>(),
        r.value("certified_frame_ms_median", 0.0), r.value("certified_frame_ms_max", 0.0),
        r.value("certified_start_error_max", 0.0),
        r.value("uncertified_frame_ms_median", 0.0), r.value("uncertified_frame_ms_max", 0.0),
        r["full_frame_ms_median"].get<double>(),
        r["full_frame_ms_max"].get<double>(), r["speedup_median"].get<double>(), r["frames_local"].get<int>(),
        r["frames"].get<int>(), r["share_median"].get<double>(), r["accuracy_max"].get<double>());
  }
  return out.str();
}

}  // namespace
}  // namespace springblend::bench

int main(int argc, char** argv) {
  springblend::ConfigureNumericalThreads(argv);  // one thread per numerical library: the paths run in parallel
  using namespace springblend::bench;
  Settings settings;
  std::string rows;
  CLI::App app{"springblend-paths-bench: target paths, path frames and their accuracy"};
  app.add_option("--rows", rows, "comma-separated rows (cylinder, cube, cheburashka, face, face-5, face-16, horse, cat)");
  app.add_option("--frames", settings.frames, "off-sample alphas per measured target")->check(CLI::Range(1, 1000));
  app.add_option("--targets", settings.targets_measured, "targets of a row whose frames are measured")
      ->check(CLI::Range(1, 1000));
  app.add_option("--shared", settings.shared, "the shared meshes (default: <repo>/../shared/meshes)");
  app.add_option("--out", settings.out, "output directory");
  app.add_flag("!--no-reference", settings.reference, "skip the tight reference (no accuracy column)");
  app.add_flag("!--no-path-span", settings.span, "path frames without the span step (SolveOptions::path_span_step)");
  app.add_option("--local-finish-share", settings.local_finish_share,
                 "largest share of the vertices a path frame's local finish may solve (SolveOptions::local_finish_share)")
      ->check(CLI::Range(0.0, 1.0));
  app.add_flag("--spool", settings.spool,
               "builds leave each path in a spool file in --out as it is solved (RigBuildControl::spool_directory), "
               "as the server's do");
  app.add_option("--path-intervals", settings.rig.path_intervals, "continuation steps per unit of weight")
      ->check(CLI::Range(1, 256));
  app.add_option("--path-max-samples", settings.rig.path_max_samples, "samples kept per target")
      ->check(CLI::Range(4, 1024));
  app.add_option("--path-tolerance", settings.rig.path_tolerance, "certified midpoint error, of the diagonal");
  std::string linear_solver = ToString(settings.rig.linear_solver);
  app.add_option("--linear-solver", linear_solver, "sparse Cholesky backend: cholmod, cholmod-double, cholmod-library (CHOLMOD's own factorization), mumps or eigen")
      ->check(CLI::IsMember({"cholmod", "cholmod-double", "cholmod-library", "mumps", "eigen"}));
  CLI11_PARSE(app, argc, argv);
  settings.rig.linear_solver = springblend::LinearSolverTypeFromString(linear_solver);
  if (settings.shared.empty()) settings.shared = settings.repo / ".." / "shared" / "meshes";
  if (!rows.empty()) {
    settings.rows.clear();
    std::stringstream in(rows);
    for (std::string r; std::getline(in, r, ',');) settings.rows.push_back(r);
  }
  const auto all = AllRows(settings.repo, settings.shared);
  json results = json::array();
  for (const std::string& name : settings.rows) {
    const auto spec = std::find_if(all.begin(), all.end(), [&](const RowSpec& r) { return r.name == name; });
    if (spec == all.end()) {
      std::cerr << "unknown row " << name << "\n";
      return 2;
    }
    std::string missing;
    for (const auto& f : spec->targets) {
      if (!fs::exists(spec->dir / f)) missing = (spec->dir / f).string();
    }
    if (!fs::exists(spec->dir / spec->rest)) missing = (spec->dir / spec->rest).string();
    if (!missing.empty()) {
      std::cout << name << ": skipped (" << missing << " not found)\n";
      results.push_back({{"row", name}, {"skipped", missing + " not found"}});
      continue;
    }
    try {
      results.push_back(RunRow(*spec, settings));
    } catch (const std::exception& e) {
      results.push_back({{"row", name}, {"skipped", e.what()}});
    }
    std::cout << Table(json::array({results.back()})) << std::flush;
  }
  fs::create_directories(settings.out);
  const std::string table = Table(results);
  std::ofstream(settings.out / "paths.md") << "# Target paths and path frames\n\n" << table;
  std::ofstream(settings.out / "paths.json") << results.dump(1);
  std::cout << "\n" << table;
  return 0;
}
