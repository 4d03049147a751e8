// springblend-bench: the paper's timing protocol (Ma et al., Table 1) on the bundled and the shared meshes.
// For every row: build the rig (the precompute), then solve the interpolation from the rest shape to the
// target in N frames (SweepFrames: frame 0 is alpha 0), warm-started, once with the default solver and once
// with the baseline configuration; compare every frame with a tightly converged reference sweep; time the
// linear blendshape. Writes OUT/bench.md, OUT/bench.json and a plot of ms per step (gnuplot, when installed),
// and prints the Markdown table.
#include <fmt/format.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <array>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <exception>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <thread>
#include <vector>

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

// The solver as shipped: what the ms/step columns measure.
std::string g_method = "newton";
SolveOptions DefaultOptions() {
  SolveOptions options;
  options.method = SolveMethodFromString(g_method);
  return options;
}
// --residual-tolerance / --step-tolerance override the default solver's (and the baseline's) tolerances.
std::optional<double> g_residual_tolerance, g_step_tolerance;
SolveOptions WithTolerances(SolveOptions options) {
  if (g_residual_tolerance) options.residual_tolerance = *g_residual_tolerance;
  if (g_step_tolerance) options.step_tolerance = *g_step_tolerance;
  return options;
}

// The "direct Newton" baseline the speed-up is measured against, run in the same process on the same sweep:
// the paper's method, warm-started from the previous frame, with a fresh factorization and a direct solve
// in every Newton iteration (and the same line search and Hessian choice as the default solver).
SolveOptions BaselineOptions() {
  SolveOptions options;
  options.reuse_factorization = false;
  return options;
}

// The reference every frame is compared with: the same sweep converged far below the default tolerances.
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

// ---- Measurements ----------------------------------------------------------------------------------------

// Figures of one pass over the sweep. Frame 0 (alpha 0, the rest shape) starts the sweep and is not an
// interpolation step, so the step figures leave it out; the termination counts include every frame.
struct StepStats {
  double median_ms = 0.0;
  double max_ms = 0.0;
  double mean_newton_iterations = 0.0;
  double mean_factorizations = 0.0;
  int max_inverted_tetrahedra = 0;
  std::map<Termination, int> terminations;

  bool all_converged() const {
    return std::all_of(terminations.begin(), terminations.end(),
                       [](const auto& entry) { return entry.first == Termination::kConverged; });
  }
};

// One solver's pass over the sweep.
struct SweepRun {
  std::vector<double> ms;  // wall time of each frame's Solve call
  std::vector<SolveSummary> summaries;
  StepStats stats;
};

struct RowResult {
  std::string name;
  std::optional<PaperFigure> paper;
  bool skipped = false;
  bool failed = false;  // an exception ended the row; what was measured before it is kept
  std::string note;
  std::optional<RigSummary> rig;
  double build_ms = 0.0;
  std::optional<SweepRun> measured, baseline, reference;
  std::optional<double> accuracy;   // max over frames of the max vertex distance to the reference / diagonal
  std::optional<double> linear_ms;  // linear blendshape, median per step

  bool ok() const {
    return !failed && (skipped || (measured && measured->stats.all_converged() && baseline &&
                                   baseline->stats.all_converged()));
  }
};

struct Settings {
  std::vector<std::string> rows;  // empty: every row
  int steps = 36;
  bool quick = false;  // also: no reference sweep, so no accuracy column
  bool profile = false;  // only the default sweep: no baseline, no reference (for perf record)
  fs::path repo = SPRINGBLEND_SOURCE_DIR;
  fs::path shared;  // default: <repo>/../shared/meshes
  fs::path out = "bench-results";
};

double Median(std::vector<double> values) {
  if (values.empty()) return 0.0;
  std::sort(values.begin(), values.end());
  const size_t n = values.size();
  return n % 2 == 1 ? values[n / 2] : 0.5 * (values[n / 2 - 1] + values[n / 2]);
}

StepStats ComputeStats(const std::vector<double>& ms, const std::vector<SolveSummary>& summaries) {
  StepStats stats;
  for (const SolveSummary& s : summaries) ++stats.terminations[s.termination];
  const std::vector<double> step_ms(ms.begin() + 1, ms.end());
  stats.median_ms = Median(step_ms);
  stats.max_ms = *std::max_element(step_ms.begin(), step_ms.end());
  for (size_t i = 1; i < summaries.size(); ++i) {
    stats.mean_newton_iterations += summaries[i].newton_iterations;
    stats.mean_factorizations += summaries[i].factorizations;
    stats.max_inverted_tetrahedra = std::max(stats.max_inverted_tetrahedra, summaries[i].inverted_tetrahedra);
  }
  stats.mean_newton_iterations /= static_cast<double>(step_ms.size());
  stats.mean_factorizations /= static_cast<double>(step_ms.size());
  return stats;
}

// Solves the sweep with a fresh solver (warm-started frame to frame when the options say so, as in the
// paper) and keeps every frame's surface positions in *positions when that is given.
SweepRun RunSweep(const std::shared_ptr<const Rig>& rig, const SolveOptions& options,
                  const std::vector<Frame>& frames, const std::string& what, std::vector<Points>* positions) {
  Solver solver(rig, options);
  SweepRun run;
  Points frame_positions;
  for (size_t i = 0; i < frames.size(); ++i) {
    const auto start = Clock::now();
    const SolveSummary summary = solver.Solve(frames[i], &frame_positions);
    run.ms.push_back(MsSince(start));
    run.summaries.push_back(summary);
    if (positions != nullptr) positions->push_back(frame_positions);
    std::cerr << fmt::format("  {} frame {}/{}: {:.1f} ms, {} Newton iterations, {} factorizations ({:.1f} ms), "
                             "{} CG iterations, {} L-BFGS, {} fallbacks, split spring {:.1f} solve {:.1f} search {:.1f} ms, {}\n",
                             what, i, frames.size() - 1, run.ms.back(), summary.newton_iterations,
                             summary.factorizations, summary.factorize_ms, summary.cg_iterations,
                             summary.lbfgs_iterations, summary.newton_fallbacks, summary.spring_ms,
                             summary.linear_solve_ms, summary.line_search_ms, ToString(summary.termination));
  }
  run.stats = ComputeStats(run.ms, run.summaries);
  return run;
}

double MaxRelativeDistance(const std::vector<Points>& a, const std::vector<Points>& b, double diagonal) {
  double worst = 0.0;
  for (size_t i = 0; i < a.size(); ++i) worst = std::max(worst, (a[i] - b[i]).rowwise().norm().maxCoeff());
  return worst / diagonal;
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
  const auto start = Clock::now();
  auto rig = Rig::Build(std::move(rest), std::move(targets));
  result->build_ms = MsSince(start);
  result->rig = rig->summary();
  return rig;
}

// Fills *result step by step, so whatever was measured before an exception stays in the report.
void MeasureRow(const RowSpec& spec, const Settings& settings, RowResult* result) {
  std::cerr << fmt::format("[{}] building the rig\n", spec.name);
  const auto rig = BuildRig(spec, result);
  const std::vector<Frame> frames = SweepFrames(spec.end_weights, settings.steps);
  std::vector<Points> measured_positions;
  result->measured = RunSweep(rig, WithTolerances(DefaultOptions()), frames, spec.name + " default", &measured_positions);
  if (settings.profile) return;
  result->baseline = RunSweep(rig, WithTolerances(BaselineOptions()), frames, spec.name + " baseline", nullptr);
  if (!settings.quick) {
    std::vector<Points> reference_positions;
    result->reference = RunSweep(rig, ReferenceOptions(), frames, spec.name + " reference", &reference_positions);
    result->accuracy = MaxRelativeDistance(measured_positions, reference_positions,
                                           BoundingBoxDiagonal(rig->rest().vertices));
    if (!result->reference->stats.all_converged()) result->note = "reference sweep not fully converged";
  }
  result->linear_ms = LinearBlendMedianMs(*rig, frames);
}

RowResult RunRow(const RowSpec& spec, const Settings& settings) {
  RowResult result;
  result.name = spec.name;
  result.paper = spec.paper;
  if (const auto missing = MissingFile(spec)) {
    result.skipped = true;
    result.note = "skipped: missing " + missing->string();
    return result;
  }
  try {
    MeasureRow(spec, settings, &result);
  } catch (const Error& e) {
    result.failed = true;
    result.note = fmt::format("error ({}): {}", ToString(e.code()), e.what());
  } catch (const std::exception& e) {
    result.failed = true;
    result.note = fmt::format("internal error: {}", e.what());
  }
  return result;
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

// ---- Markdown --------------------------------------------------------------------------------------------

template <typename T, typename Format>
std::string Cell(const std::optional<T>& value, Format&& format) {
  return value ? format(*value) : "-";
}

std::string Terminations(const StepStats& stats) {
  std::vector<std::string> parts;
  for (const auto& [termination, count] : stats.terminations) {
    parts.push_back(fmt::format("{} {}", ToString(termination), count));
  }
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

// The table's columns; TableRow gives one cell per column, in this order.
const std::vector<std::string> kColumns = {
    "row", "vertices", "springs", "tets", "interior", "precompute ms", "ms/step median", "ms/step max",
    "Newton it/step", "factorizations/step", "inverted tets max", "accuracy", "linear ms/step",
    "baseline ms/step", "speed-up", "terminations", "paper CPU s/step", "note"};

std::string TableRow(const RowResult& r) {
  const auto stats = [](const std::optional<SweepRun>& run) {
    return run ? std::optional<StepStats>(run->stats) : std::nullopt;
  };
  const auto measured = stats(r.measured);
  const auto baseline = stats(r.baseline);
  const std::string speedup =
      measured && baseline ? fmt::format("{:.1f}x", baseline->median_ms / measured->median_ms) : "-";
  const std::vector<std::string> cells = {
      r.name,
      Cell(r.rig, [](const RigSummary& s) { return std::to_string(s.vertices); }),
      Cell(r.rig, [](const RigSummary& s) { return std::to_string(s.springs); }),
      Cell(r.rig, [](const RigSummary& s) { return std::to_string(s.tetrahedra); }),
      Cell(r.rig, [](const RigSummary& s) { return s.interior; }),
      Cell(r.rig, [&](const RigSummary&) { return fmt::format("{:.0f}", r.build_ms); }),
      Cell(measured, [](const StepStats& s) { return fmt::format("{:.1f}", s.median_ms); }),
      Cell(measured, [](const StepStats& s) { return fmt::format("{:.1f}", s.max_ms); }),
      Cell(measured, [](const StepStats& s) { return fmt::format("{:.2f}", s.mean_newton_iterations); }),
      Cell(measured, [](const StepStats& s) { return fmt::format("{:.2f}", s.mean_factorizations); }),
      Cell(measured, [](const StepStats& s) { return std::to_string(s.max_inverted_tetrahedra); }),
      Cell(r.accuracy, [](double a) { return fmt::format("{:.1e}", a); }),
      Cell(r.linear_ms, [](double ms) { return fmt::format("{:.3f}", ms); }),
      Cell(baseline, [](const StepStats& s) { return fmt::format("{:.1f}", s.median_ms); }),
      speedup,
      Cell(measured, Terminations),
      Cell(r.paper, [](const PaperFigure& p) {
        return fmt::format("{:.2f} s ({:.1f}k, {:.1f}k)", p.cpu_s_per_step, p.vertices_k, p.springs_k);
      }),
      Escape(r.note),
  };
  return fmt::format("| {} |", fmt::join(cells, " | "));
}

std::string MarkdownReport(const Machine& machine, const Settings& settings, const std::vector<RowResult>& rows) {
  std::string md = "# springblend-bench\n\n";
  md += fmt::format("machine: nproc {}, {}, date {}, git {}\n\n", machine.nproc, machine.cpu, machine.date,
                    machine.git);
  md += fmt::format(
      "Protocol (paper Table 1): {} frames from the rest shape (frame 0, alpha 0) to the target, warm-started. "
      "Step figures are over frames 1..{} (time of each Solve call); terminations count every frame. "
      "Accuracy: max over frames of the max vertex distance to a reference sweep (residual and step "
      "tolerance 1e-12), relative to the bounding-box diagonal{}. Speed-up: baseline median / default median. "
      "Paper: 2.66 GHz Core 2 Quad, PARDISO, s/step (vertices, springs).\n\n",
      settings.steps, settings.steps - 1, settings.quick ? " (skipped: --quick)" : "");
  md += fmt::format("| {} |\n", fmt::join(kColumns, " | "));
  md += fmt::format("|{}\n", fmt::join(std::vector<std::string>(kColumns.size(), "---|"), ""));
  for (const RowResult& row : rows) md += TableRow(row) + "\n";
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
          {"notes", s.notes}};
}

json RunJson(const SweepRun& run) {
  json terminations = json::object();
  for (const auto& [termination, count] : run.stats.terminations) terminations[ToString(termination)] = count;
  json frames = json::array();
  for (size_t i = 0; i < run.summaries.size(); ++i) {
    const SolveSummary& s = run.summaries[i];
    frames.push_back({{"frame", i},
                      {"ms", run.ms[i]},
                      {"solve_ms", s.solve_ms},
                      {"factorize_ms", s.factorize_ms},
                      {"newton_iterations", s.newton_iterations},
                      {"factorizations", s.factorizations},
                      {"cg_iterations", s.cg_iterations},
                      {"line_search_halvings", s.line_search_halvings},
                      {"residual", s.residual},
                      {"inverted_tetrahedra", s.inverted_tetrahedra},
                      {"termination", ToString(s.termination)}});
  }
  return {{"median_ms", run.stats.median_ms},
          {"max_ms", run.stats.max_ms},
          {"mean_newton_iterations", run.stats.mean_newton_iterations},
          {"mean_factorizations", run.stats.mean_factorizations},
          {"max_inverted_tetrahedra", run.stats.max_inverted_tetrahedra},
          {"terminations", terminations},
          {"frames", frames}};
}

template <typename T, typename ToJson>
json OrNull(const std::optional<T>& value, ToJson&& to_json) {
  return value ? to_json(*value) : json(nullptr);
}

json RowJson(const RowResult& r) {
  const auto identity = [](double x) { return json(x); };
  return {{"name", r.name},
          {"skipped", r.skipped},
          {"failed", r.failed},
          {"note", r.note},
          {"rig", OrNull(r.rig, RigJson)},
          {"build_ms", r.rig ? json(r.build_ms) : json(nullptr)},
          {"default", OrNull(r.measured, RunJson)},
          {"baseline", OrNull(r.baseline, RunJson)},
          {"reference", OrNull(r.reference, RunJson)},
          {"accuracy", OrNull(r.accuracy, identity)},
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
                 {"rows", json::array()}};
  for (const RowResult& row : rows) report["rows"].push_back(RowJson(row));
  return report;
}

// ---- Plot ------------------------------------------------------------------------------------------------

// Writes the data and the gnuplot script (kept so the plot can be redrawn elsewhere) and runs gnuplot when
// it is installed. The plot is a convenience: nothing here fails the run.
void PlotMsPerStep(const std::vector<RowResult>& rows, const fs::path& out) {
  std::ofstream data(out / "ms_per_step.dat");
  std::vector<std::string> plots;
  size_t steps = 1;
  for (const RowResult& row : rows) {
    if (!row.measured) continue;
    steps = std::max(steps, row.measured->ms.size() - 1);
    // gnuplot's `index` counts blocks separated by two blank lines.
    data << "# " << row.name << "\n";
    for (size_t i = 1; i < row.measured->ms.size(); ++i) data << i << " " << row.measured->ms[i] << "\n";
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
            "  set terminal pngcairo size 1000,600\n"
            "} else {\n"
            "  set terminal png size 1000,600\n"
            "}\n"
            "set output 'ms_per_step.png'\n"
            "set title 'springblend: ms per interpolation step (default solver)'\n"
            "set xlabel 'frame (alpha = frame / (steps - 1))'\n"
            "set ylabel 'ms (log scale)'\n"
            "set logscale y\n"
            "set grid\n"
            "set key outside right noenhanced\n"
         << fmt::format("set xtics {}\n", std::max<size_t>(1, steps / 12))  // whole frames, about a dozen
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

// Exit status: 0 when every selected row was measured and converged (or skipped for lack of files),
// 1 when a row failed or a frame did not converge, 2 for bad options.
int Run(const Settings& settings) {
  const std::vector<RowSpec> specs = SelectRows(settings);
  std::error_code ec;
  fs::create_directories(settings.out, ec);
  if (ec || !fs::is_directory(settings.out)) {
    throw Error(ErrorCode::kInvalidInput, "cannot create the output directory " + settings.out.string());
  }
  const Machine machine = DescribeMachine(settings.repo);
  std::vector<RowResult> rows;
  for (const RowSpec& spec : specs) {
    rows.push_back(RunRow(spec, settings));
    // After every row, so a long run that is stopped keeps the rows it finished.
    WriteReports(machine, settings, rows);
  }
  PlotMsPerStep(rows, settings.out);
  std::cout << MarkdownReport(machine, settings, rows);
  const bool ok = std::all_of(rows.begin(), rows.end(), [](const RowResult& row) { return row.ok(); });
  return ok ? 0 : 1;
}

int Main(int argc, char** argv) {
  Settings settings;
  CLI::App app{"springblend-bench: the paper's timing protocol (36 warm-started steps from the rest shape to "
               "the target) on the bundled and the shared meshes"};
  app.add_option("--rows", settings.rows,
                 "comma-separated subset of: cylinder, cube, cheburashka, face, face-mix, horse, cat")
      ->delimiter(',');
  CLI::Option* steps = app.add_option("--steps", settings.steps, "frames per sweep, including frame 0 (default 36)")
                           ->check(CLI::Range(2, 100000));
  app.add_flag("--quick", settings.quick, "6 frames (unless --steps is given) and no reference sweep");
  app.add_flag("--profile", settings.profile,
               "run only the default solver's sweep (no baseline, no reference), e.g. under perf record");
  app.add_option("--repo", settings.repo, "the springblend source tree (for tests/data and git describe)");
  app.add_option("--shared", settings.shared, "the shared meshes (default: <repo>/../shared/meshes)");
  app.add_option("--out", settings.out, "output directory for bench.md, bench.json and the plot");
  app.add_option("--method", g_method, "the measured solve method: newton, newton-laplacian or lbfgs");
  app.add_option("--residual-tolerance", g_residual_tolerance, "override SolveOptions::residual_tolerance");
  app.add_option("--step-tolerance", g_step_tolerance, "override SolveOptions::step_tolerance");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
  }
  if (settings.quick && steps->count() == 0) settings.steps = 6;
  if (settings.shared.empty()) settings.shared = settings.repo / ".." / "shared" / "meshes";
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
