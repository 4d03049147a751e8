// springblend-bake-bench: how much of the physics a baked plain blendshape rig (springblend/bake.h) plays
// without a solver. Per row (a rest mesh and its targets): the rig build, the bake (its solved frames, the
// in-betweens it chose, the pairs it kept, its time and size), then, against frames solved in the same run, the
// largest and mean distance (of the bounding-box diagonal) of the baked rig's linear evaluation and of the plain
// linear blendshape: single-target frames at --alphas weights per target that the bake never solved, random
// two-target pairs and random five-target mixes (weights in [0.2, 1], a fixed seed); beside it, as the baseline of
// the same run, the same bake with the solved frames as in-betweens (BakeOptions::solved_inbetweens; its frames
// are the first bake's, remembered, so it costs no solve).
// Rows whose meshes are absent are skipped with a line. Prints a Markdown table and writes OUT/bake.md and
// OUT/bake.json.
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
#include <random>
#include <string>
#include <vector>

#include "springblend/bake.h"
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

double SecondsSince(Clock::time_point start) { return std::chrono::duration<double>(Clock::now() - start).count(); }

struct RowSpec {
  std::string name;
  fs::path dir;
  std::string rest;
  std::vector<std::string> targets;
};

std::vector<RowSpec> AllRows(const fs::path& repo, const fs::path& shared) {
  const fs::path data = repo / "tests" / "data";
  return {
      {"cylinder", data / "cylinder", "cylinder.obj", {"poses-2_cylinder-1.obj", "poses-2_cylinder-3.obj"}},
      {"face-5",
       shared / "face6706",
       "generic_neutral_mesh.obj",
       {"jawOpen.obj", "mouthSmile_L.obj", "mouthSmile_R.obj", "eyeBlink_L.obj", "browInnerUp_L.obj"}},
      {"horse", shared / "horse", "horse-reference.obj", {"horse-01.obj", "horse-02.obj"}},
      {"cat", shared / "cat", "cat-reference.obj", {"cat-01.obj", "cat-02.obj"}},
  };
}

struct Errors {
  double max = 0.0, sum = 0.0;
  int count = 0;
  std::vector<double> worst;  // the weights of the frame with the largest error
  void Add(double e, const std::vector<double>& weights) {
    if (count == 0 || e > max) worst = weights;
    max = std::max(max, e);
    sum += e;
    ++count;
  }
  double mean() const { return count > 0 ? sum / count : 0.0; }
  json Json() const { return {{"max", max}, {"mean", mean()}, {"frames", count}, {"worst_weights", worst}}; }
};

double Distance(const Points& a, const Points& b) { return std::sqrt((a - b).rowwise().squaredNorm().maxCoeff()); }

struct Settings {
  fs::path repo = SPRINGBLEND_SOURCE_DIR;
  fs::path shared;
  fs::path out = "bench-results";
  std::vector<std::string> rows = {"cylinder", "face-5", "horse", "cat"};
  int alphas = 17;
  int pairs = 8;
  int mixes = 8;
  BakeOptions bake;
};

json RunRow(const RowSpec& spec, const Settings& settings) {
  json row;
  row["row"] = spec.name;
  std::vector<TriangleMesh> targets;
  for (const auto& t : spec.targets) targets.push_back(LoadMesh((spec.dir / t).string()));
  const auto build_start = Clock::now();
  const auto rig = Rig::Build(LoadMesh((spec.dir / spec.rest).string()), std::move(targets));
  row["build_s"] = SecondsSince(build_start);
  const int m = rig->num_targets();
  const double diagonal = rig->summary().bounding_box_diagonal;
  row["targets"] = m;
  row["vertices"] = rig->num_surface_vertices();

  // Frames are a function of their weights alone: the baseline bake reuses the first bake's.
  const FrameSource solve = LocalFrameSource(rig);
  std::map<std::vector<double>, SolvedShape> remembered;
  const FrameSource frames = [&](const std::vector<std::vector<double>>& weights, std::vector<SolvedShape>* out) {
    std::vector<std::vector<double>> missing;
    for (const auto& w : weights) {
      if (!remembered.count(w)) missing.push_back(w);
    }
    if (!missing.empty()) {
      std::vector<SolvedShape> solved;
      solve(missing, &solved);
      for (size_t i = 0; i < missing.size(); ++i) remembered[missing[i]] = std::move(solved[i]);
    }
    out->clear();
    for (const auto& w : weights) out->push_back(remembered.at(w));
  };
  const auto bake_start = Clock::now();
  const BakedRig baked = BakeRig(BakeInputOf(*rig), frames, settings.bake);
  row["bake_s"] = SecondsSince(bake_start);
  row["inbetweens_s"] = baked.summary.inbetweens_ms / 1000.0;
  BakeOptions on_path = settings.bake;
  on_path.solved_inbetweens = true;
  on_path.progress = nullptr;
  const BakedRig baseline = BakeRig(BakeInputOf(*rig), frames, on_path);
  int shapes = 0;
  json inbetweens = json::array();
  for (const BakedTarget& t : baked.targets) {
    std::vector<double> w;
    for (const BakedShape& s : t.inbetweens) w.push_back(s.weight);
    inbetweens.push_back({{"target", t.name},
                          {"weights", w},
                          {"snaps", t.snaps},
                          {"max_error", t.max_error},
                          {"floor", t.floor}});
    shapes += 1 + static_cast<int>(t.inbetweens.size());
  }
  shapes += static_cast<int>(baked.combinations.size());
  row["inbetweens"] = inbetweens;
  row["floor"] = baked.summary.floor;
  row["pair_floor"] = baked.summary.pair_floor;
  row["frames_solved"] = baked.summary.frames;
  row["candidate_pairs"] = baked.summary.candidate_pairs;
  row["kept_pairs"] = baked.summary.kept_pairs;
  row["refused_pairs"] = baked.summary.refused_pairs;
  row["combinations"] = baked.combinations.size();
  // As float32 positions, what a DCC or engine keeps per shape.
  row["size_mb"] = static_cast<double>(shapes) * rig->num_surface_vertices() * 3 * sizeof(float) / (1024.0 * 1024.0);

  // Held-out frames, solved in one batch.
  std::vector<std::vector<double>> single, pairs, mixes;
  for (int t = 0; t < m; ++t) {
    for (int j = 0; j < settings.alphas; ++j) {
      std::vector<double> w(m, 0.0);
      w[t] = (j + 0.5) / settings.alphas;
      single.push_back(std::move(w));
    }
  }
  std::mt19937 random(20261202);
  std::uniform_real_distribution<double> weight(0.2, 1.0);
  if (m >= 2) {
    for (int k = 0; k < settings.pairs; ++k) {
      std::vector<int> order(m);
      for (int t = 0; t < m; ++t) order[t] = t;
      std::shuffle(order.begin(), order.end(), random);
      std::vector<double> w(m, 0.0);
      w[order[0]] = weight(random);
      w[order[1]] = weight(random);
      pairs.push_back(std::move(w));
    }
  }
  if (m >= 3) {
    for (int k = 0; k < settings.mixes; ++k) {
      std::vector<int> order(m);
      for (int t = 0; t < m; ++t) order[t] = t;
      std::shuffle(order.begin(), order.end(), random);
      std::vector<double> w(m, 0.0);
      for (int i = 0; i < std::min(m, 5); ++i) w[order[i]] = weight(random);
      mixes.push_back(std::move(w));
    }
  }
  const auto measure = [&](const std::vector<std::vector<double>>& weights, const char* key) {
    if (weights.empty()) return;
    std::vector<SolvedShape> solved;
    const auto start = Clock::now();
    solve(weights, &solved);
    Errors bake, on_solved, linear;
    int unconverged = 0;
    for (size_t i = 0; i < weights.size(); ++i) {
      unconverged += solved[i].converged ? 0 : 1;
      bake.Add(Distance(baked.Evaluate(weights[i]), solved[i].positions) / diagonal, weights[i]);
      on_solved.Add(Distance(baseline.Evaluate(weights[i]), solved[i].positions) / diagonal, weights[i]);
      linear.Add(Distance(LinearBlend(*rig, weights[i]), solved[i].positions) / diagonal, weights[i]);
    }
    row[key] = {{"baked", bake.Json()}, {"solved_inbetweens", on_solved.Json()}, {"linear", linear.Json()}, {"unconverged", unconverged},
                {"solve_s", SecondsSince(start)}};
  };
  measure(single, "single");
  measure(pairs, "pairs");
  measure(mixes, "mixes");
  return row;
}

std::string Cell(const json& row, const char* key, const char* which) {
  if (!row.contains(key)) return "-";
  return fmt::format("{:.1e} / {:.1e}", row[key][which]["max"].get<double>(), row[key][which]["mean"].get<double>());
}

std::string Table(const json& rows) {
  std::string out =
      "| row | targets | in-betweens per target | pairs kept (of candidates) | rig build s | bake s | of which in-betweens s | size MB | single: "
      "baked | single: floor | single: solved in-betweens | single: linear | pairs: baked | pairs: floor | pairs: solved in-betweens | pairs: linear "
      "| 5-mixes: baked | 5-mixes: linear |\n"
      "| --- | ---: | --- | --- | ---: | ---: | ---: | ---: | --- | ---: | --- | --- | --- | ---: | --- | --- | --- | --- |\n";
  for (const json& r : rows) {
    if (r.contains("skipped")) {
      out += fmt::format("| {} | skipped: {} |\n", r["row"].get<std::string>(), r["skipped"].get<std::string>());
      continue;
    }
    std::string counts;
    for (const json& t : r["inbetweens"]) counts += (counts.empty() ? "" : ", ") + std::to_string(t["weights"].size());
    out += fmt::format("| {} | {} | {} | {} ({}) | {:.1f} | {:.1f} | {:.1f} | {:.1f} | {} | {:.1e} | {} | {} | {} | {:.1e} | {} | {} | {} | {} |\n",
                       r["row"].get<std::string>(), r["targets"].get<int>(), counts, r["kept_pairs"].get<int>(),
                       r["candidate_pairs"].get<int>(), r["build_s"].get<double>(), r["bake_s"].get<double>(), r["inbetweens_s"].get<double>(),
                       r["size_mb"].get<double>(), Cell(r, "single", "baked"), r["floor"].get<double>(),
                       Cell(r, "single", "solved_inbetweens"),
                       Cell(r, "single", "linear"), Cell(r, "pairs", "baked"), r["pair_floor"].get<double>(),
                       Cell(r, "pairs", "solved_inbetweens"),
                       Cell(r, "pairs", "linear"), Cell(r, "mixes", "baked"),
                       Cell(r, "mixes", "linear"));
  }
  out += "\nErrors: largest / mean distance of a vertex from the solved frame, of the bounding-box diagonal. Baked: "
         "in-betweens fitted to the path (the default); solved in-betweens: the same bake keeping the solved frames "
         "(--solved-inbetweens), the baseline. Floor: a lower bound, at the bake's solved samples, of the largest "
         "error of any rig that plays each target piecewise linearly with as many in-betweens (the largest over the "
         "targets; BakedTarget::floor). Pairs' floor: a lower bound, at the candidate pairs' solved frames on the grid "
         "{0, 1/2, 1}^2, of the largest error of any rig that plays each target alone however it likes plus a "
         "corrective on by the product of the weights (BakeSummary::pair_floor).\n";
  return out;
}

int Main(int argc, char** argv) {
  ConfigureNumericalThreads(argv);
  Settings settings;
  CLI::App app{"springblend-bake-bench: a baked plain blendshape rig against the solved frames"};
  std::string shared;
  app.add_option("--shared", shared, "the shared meshes (default: ../shared/meshes beside the repository)");
  app.add_option("--out", settings.out, "directory for bake.md and bake.json");
  app.add_option("--rows", settings.rows, "rows to run: cylinder, face-5, horse, cat")->delimiter(',');
  app.add_option("--alphas", settings.alphas, "held-out weights per target")->check(CLI::Range(1, 1000));
  app.add_option("--pairs", settings.pairs, "random two-target frames")->check(CLI::Range(0, 1000));
  app.add_option("--mixes", settings.mixes, "random five-target frames")->check(CLI::Range(0, 1000));
  app.add_option("--inbetweens", settings.bake.inbetweens, "in-betweens per target");
  app.add_option("--samples", settings.bake.samples, "path samples per target");
  app.add_option("--pair-threshold", settings.bake.pair_threshold, "a pair's corrective threshold");
  CLI11_PARSE(app, argc, argv);
  settings.shared = shared.empty() ? settings.repo.parent_path() / "shared" / "meshes" : fs::path(shared);
  json rows = json::array();
  for (const std::string& name : settings.rows) {
    const auto all = AllRows(settings.repo, settings.shared);
    const auto it = std::find_if(all.begin(), all.end(), [&](const RowSpec& r) { return r.name == name; });
    if (it == all.end()) {
      std::cerr << "springblend-bake-bench: unknown row '" << name << "'\n";
      return 2;
    }
    if (!fs::exists(it->dir / it->rest)) {
      std::cout << "row " << name << ": skipped, " << (it->dir / it->rest).string() << " is absent" << std::endl;
      rows.push_back({{"row", name}, {"skipped", (it->dir / it->rest).string() + " is absent"}});
      continue;
    }
    std::cout << "row " << name << " ..." << std::endl;
    rows.push_back(RunRow(*it, settings));
    std::cout << rows.back().dump() << std::endl;
  }
  const std::string table = Table(rows);
  std::cout << "\n" << table;
  fs::create_directories(settings.out);
  std::ofstream(settings.out / "bake.md") << "# Baked plain rigs against solved frames\n\n" << table;
  std::ofstream(settings.out / "bake.json") << rows.dump(1) << "\n";
  return 0;
}

}  // namespace
}  // namespace springblend::bench

int main(int argc, char** argv) {
  try {
    return springblend::bench::Main(argc, argv);
  } catch (const springblend::Error& e) {
    std::cerr << "springblend-bake-bench: " << e.what() << "\n";
    return 1;
  }
}
