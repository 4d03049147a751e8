// Rig files (issue 18): what LoadRigFile reads from the bundled cylinder rig, every bad rig file refused with a
// message naming the file, the target and the field, and the production-rig semantics on the cylinder built
// from a rig file: in-betweens and combinations reproduced, all-zero and all-one masks.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <fmt/format.h>

#include <nlohmann/json.hpp>

#include "rig_file.h"
#include "test_util.h"

namespace springblend::cli {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;
using springblend::testing::CatchError;
using springblend::testing::DataPath;
using springblend::testing::MaxDistance;
using springblend::testing::TempDir;

const std::string kRig = DataPath("cylinder/rig.json");

std::string Cylinder(const std::string& file) { return DataPath("cylinder/" + file); }

// A rig file in `dir` from JSON whose mesh paths are absolute (paths relative to the rig file join them as given).
std::string WriteRig(const TempDir& dir, const nlohmann::json& rig, const std::string& name = "rig.json") {
  return dir.Write(name, rig.dump(1));
}

nlohmann::json GoodRig() {
  return nlohmann::json::parse(fmt::format(R"({{
    "rest": "{0}/cylinder.obj",
    "targets": [
      {{"name": "bend", "mesh": "{0}/poses-2_cylinder-2.obj",
        "inbetweens": [{{"weight": 0.5, "mesh": "{0}/poses-2_cylinder-1.obj"}}]}},
      {{"name": "twist", "mesh": "{0}/poses-2_cylinder-3.obj", "mask": "{0}/twist_mask.txt"}},
      {{"name": "bend_twist", "mesh": "{0}/poses-2_cylinder-4.obj", "combination": ["bend", "twist"]}}]}})",
                                           DataPath("cylinder")));
}

TEST(RigFile, ReadsTheBundledCylinderRig) {
  const RigFile rig = LoadRigFile(kRig);
  EXPECT_EQ(rig.path, kRig);
  EXPECT_EQ(rig.rest.vertices.rows(), 420);
  ASSERT_EQ(rig.targets.size(), 3u);
  EXPECT_EQ(rig.WeightNames(), (std::vector<std::string>{"bend", "twist"}));
  EXPECT_EQ(rig.targets[0].mesh.name, "bend");
  ASSERT_EQ(rig.targets[0].inbetweens.size(), 1u);
  EXPECT_EQ(rig.targets[0].inbetweens[0].weight, 0.5);
  EXPECT_EQ(rig.targets[0].inbetweens[0].mesh.vertices, LoadMesh(Cylinder("poses-2_cylinder-1.obj")).vertices);
  ASSERT_EQ(rig.targets[1].mask.size(), 420u);
  EXPECT_EQ(*std::min_element(rig.targets[1].mask.begin(), rig.targets[1].mask.end()), 0.0);
  EXPECT_EQ(*std::max_element(rig.targets[1].mask.begin(), rig.targets[1].mask.end()), 1.0);
  EXPECT_EQ(rig.targets[2].combination, (std::vector<std::string>{"bend", "twist"}));
  EXPECT_TRUE(rig.targets[2].mask.empty());
}

TEST(RigFile, InlineMaskEqualsTheMaskFile) {
  TempDir dir;
  nlohmann::json rig = GoodRig();
  const std::vector<double> file_mask = LoadRigFile(kRig).targets[1].mask;
  rig["targets"][1]["mask"] = file_mask;
  rig["fixed_vertices"] = {3, 7};
  const RigFile loaded = LoadRigFile(WriteRig(dir, rig));
  EXPECT_EQ(loaded.targets[1].mask, file_mask);
  EXPECT_EQ(loaded.fixed_vertices, (std::vector<int>{3, 7}));
}

TEST(RigFile, MaskTextSkipsCommentsAndNamesTheBadLine) {
  EXPECT_EQ(ParseMaskText("# a mask\n0.5\n\n 1 \r\n0\n", "m.txt"), (std::vector<double>{0.5, 1.0, 0.0}));
  EXPECT_THAT(CatchError([] { ParseMaskText("0.5\n1\nabc\n", "m.txt"); }).what(),
              AllOf(HasSubstr("m.txt: line 3"), HasSubstr("'abc' is not a number")));
  EXPECT_THAT(CatchError([] { ParseMaskText("0.5\ninf\n", "m.txt"); }).what(), HasSubstr("m.txt: line 2"));
}

// Each bad file: an edit of the good rig, and what the message must say (besides the rig file's path).
struct BadRig {
  std::string what;
  std::function<void(nlohmann::json&, const TempDir&)> edit;
  std::vector<std::string> message;
};

std::vector<BadRig> JsonLevelCases() {
  return {
      {"unknown top-level key", [](auto& r, auto&) { r["rst"] = 1; }, {"unknown key 'rst'"}},
      {"unknown target key", [](auto& r, auto&) { r["targets"][1]["maks"] = "x"; }, {"targets[1]", "unknown key 'maks'"}},
      {"unknown in-between key", [](auto& r, auto&) { r["targets"][0]["inbetweens"][0]["w"] = 0.5; },
       {"target 'bend': inbetweens[0]", "unknown key 'w'"}},
      {"rest missing", [](auto& r, auto&) { r.erase("rest"); }, {"'rest' is missing"}},
      {"target without mesh", [](auto& r, auto&) { r["targets"][0].erase("mesh"); }, {"targets[0]", "'mesh' is missing"}},
      {"targets not a list", [](auto& r, auto&) { r["targets"] = "bend"; }, {"targets: expected a list, got string"}},
      {"no targets", [](auto& r, auto&) { r["targets"] = nlohmann::json::array(); }, {"targets is empty"}},
      {"name a number", [](auto& r, auto&) { r["targets"][0]["name"] = 7; }, {"targets[0].name: expected a string, got number"}},
      {"weight a string", [](auto& r, auto&) { r["targets"][0]["inbetweens"][0]["weight"] = "half"; },
       {"target 'bend': inbetweens[0].weight: expected a number, got string"}},
      {"inbetweens an object", [](auto& r, auto&) { r["targets"][0]["inbetweens"] = nlohmann::json::object(); },
       {"target 'bend': inbetweens: expected a list, got object"}},
      {"mask an object", [](auto& r, auto&) { r["targets"][1]["mask"] = nlohmann::json::object(); },
       {"target 'twist': mask: expected a list of weights"}},
      {"mask value a string", [](auto& r, auto&) { r["targets"][1]["mask"] = std::vector<std::string>(420, "1"); },
       {"target 'twist': mask[0]: expected a number, got string"}},
      {"combination a string", [](auto& r, auto&) { r["targets"][2]["combination"] = "bend"; },
       {"target 'bend_twist': combination: expected a list, got string"}},
      {"fixed vertex out of range", [](auto& r, auto&) { r["fixed_vertices"] = {1, 420}; },
       {"fixed_vertices[1]: 420 is not a vertex"}},
      {"missing mesh file", [](auto& r, auto&) { r["targets"][0]["mesh"] = "nowhere.obj"; },
       {"target 'bend': mesh: file not found", "nowhere.obj"}},
      {"missing in-between file", [](auto& r, auto&) { r["targets"][0]["inbetweens"][0]["mesh"] = "half.obj"; },
       {"target 'bend': inbetweens[0].mesh: file not found", "half.obj"}},
      {"missing mask file", [](auto& r, auto&) { r["targets"][1]["mask"] = "mask.txt"; },
       {"target 'twist': mask: file not found", "mask.txt"}},
      {"inline mask of the wrong length", [](auto& r, auto&) { r["targets"][1]["mask"] = std::vector<double>(419, 1.0); },
       {"target 'twist': mask: 419 values, but the rest mesh", "has 420 vertices"}},
      {"mask file of the wrong length",
       [](auto& r, const TempDir& dir) { r["targets"][1]["mask"] = dir.Write("short.txt", "1\n0\n"); },
       {"target 'twist': mask: 2 values in", "short.txt", "420 vertices"}},
      {"mask file with a bad line",
       [](auto& r, const TempDir& dir) { r["targets"][1]["mask"] = dir.Write("bad.txt", "1\n0\nx1\n"); },
       {"target 'twist': mask", "bad.txt: line 3: 'x1' is not a number"}},
      {"a target name with '='", [](auto& r, auto&) { r["targets"][1]["name"] = "twist=1"; },
       {"targets[1].name 'twist=1' contains '='", "could not address it"}},
      {"a target name with ','", [](auto& r, auto&) { r["targets"][0]["name"] = "bend,left"; },
       {"targets[0].name 'bend,left' contains ','"}},
      {"two combinations of the same drivers",
       [](auto& r, auto&) {
         nlohmann::json again = r["targets"][2];
         again["name"] = "twist_bend";
         again["combination"] = {"twist", "bend"};
         r["targets"].push_back(again);
       },
       {"target 'twist_bend': combination has the drivers of target 'bend_twist'"}},
      {"a mesh that does not parse",
       [](auto& r, const TempDir& dir) { r["targets"][1]["mesh"] = dir.Write("broken.obj", "v 0 0 0\nf 1 2 3\n"); },
       {"target 'twist': mesh", "broken.obj"}},
  };
}

TEST(RigFile, RefusesEveryJsonLevelMistakeNamingFileTargetAndField) {
  for (const BadRig& bad : JsonLevelCases()) {
    TempDir dir;
    nlohmann::json rig = GoodRig();
    bad.edit(rig, dir);
    const std::string path = WriteRig(dir, rig);
    const std::string message = CatchError([&] { LoadRigFile(path); }).what();
    EXPECT_THAT(message, HasSubstr(path + ": ")) << bad.what;
    for (const auto& part : bad.message) EXPECT_THAT(message, HasSubstr(part)) << bad.what;
  }
  TempDir dir;
  EXPECT_THAT(CatchError([&] { LoadRigFile(dir.Write("rig.json", "{\"rest\": ")); }).what(), HasSubstr("not valid JSON"));
  EXPECT_THAT(CatchError([&] { LoadRigFile(dir.File("none.json")); }).what(), HasSubstr("none.json"));
  EXPECT_EQ(CatchError([&] { LoadRigFile(dir.File("none.json")); }).code(), ErrorCode::kNotFound);
}

// The rig's own rules are the solver's: BuildRig puts the rig file's path in front of its message.
TEST(RigFile, SolverRefusalsNameTheRigFileTargetAndField) {
  const std::vector<BadRig> cases = {
      {"in-between weight above 1", [](auto& r, auto&) { r["targets"][0]["inbetweens"][0]["weight"] = 1.5; },
       {"target 'bend'", "inbetweens[0].weight", "1.5"}},
      {"in-between weight 0", [](auto& r, auto&) { r["targets"][0]["inbetweens"][0]["weight"] = 0.0; },
       {"target 'bend'", "inbetweens[0].weight"}},
      {"repeated in-between weight",
       [](auto& r, auto&) { r["targets"][0]["inbetweens"].push_back(r["targets"][0]["inbetweens"][0]); },
       {"target 'bend'", "inbetweens[1].weight"}},
      {"combination of an unknown target", [](auto& r, auto&) { r["targets"][2]["combination"][1] = "smile"; },
       {"target 'bend_twist'", "combination", "smile"}},
      {"combination of a combination",
       [](auto& r, auto&) {
         r["targets"].push_back({{"name", "triple"}, {"mesh", r["targets"][2]["mesh"]}, {"combination", {"bend", "bend_twist"}}});
       },
       {"target 'triple'", "combination", "bend_twist"}},
      {"a mesh of another topology",
       [](auto& r, auto&) { r["targets"][1]["mesh"] = DataPath("cube/poses-1_cube-1.obj"); },
       {"twist", "poses-1_cube-1.obj"}},
      {"repeated target name", [](auto& r, auto&) { r["targets"][1]["name"] = "bend"; }, {"target 'bend'", "name"}},
  };
  for (const BadRig& bad : cases) {
    TempDir dir;
    nlohmann::json rig = GoodRig();
    bad.edit(rig, dir);
    const std::string path = WriteRig(dir, rig);
    const Error error = CatchError([&] { BuildRig(LoadRigFile(path), RigOptions{}); });
    EXPECT_EQ(error.code(), ErrorCode::kInvalidInput) << bad.what;
    EXPECT_THAT(error.what(), HasSubstr(path + ": ")) << bad.what;
    for (const auto& part : bad.message) EXPECT_THAT(error.what(), HasSubstr(part)) << bad.what;
  }
}

// ---------------------------------------------------------------------------------------------------------
// Semantics on the cylinder: everything to 1e-6 of the bounding-box diagonal.

Points Solve(const std::shared_ptr<const Rig>& rig, const std::vector<double>& weights) {
  Solver solver(rig);
  Points positions;
  const SolveSummary summary = solver.Solve(Frame{weights}, &positions);
  EXPECT_TRUE(summary.converged()) << summary.message;
  return positions;
}

class RigSemantics : public ::testing::Test {
 protected:
  // No target paths: the rig file's semantics do not depend on where a frame's solve starts.
  static void SetUpTestSuite() {
    rig_ = new std::shared_ptr<const Rig>(BuildRig(LoadRigFile(kRig), testing::NoPathsRigOptions()));
  }
  static void TearDownTestSuite() { delete rig_; }
  static const std::shared_ptr<const Rig>& rig() { return *rig_; }
  static double Tolerance() { return 1e-6 * BoundingBoxDiagonal(LoadMesh(Cylinder("cylinder.obj")).vertices); }
  static inline std::shared_ptr<const Rig>* rig_ = nullptr;
};

TEST_F(RigSemantics, WeightsAreTheTargetsThatAreNotCombinations) {
  EXPECT_EQ(rig()->num_targets(), 2);
  EXPECT_EQ(rig()->target_names(), (std::vector<std::string>{"bend", "twist"}));
  EXPECT_EQ(rig()->combination_names(), (std::vector<std::string>{"bend_twist"}));
}

TEST_F(RigSemantics, InbetweenIsReproducedAtItsWeightAndTheTargetAtOne) {
  EXPECT_LE(MaxDistance(Solve(rig(), {0.5, 0.0}), LoadMesh(Cylinder("poses-2_cylinder-1.obj")).vertices), Tolerance());
  EXPECT_LE(MaxDistance(Solve(rig(), {1.0, 0.0}), LoadMesh(Cylinder("poses-2_cylinder-2.obj")).vertices), Tolerance());
}

TEST_F(RigSemantics, CombinationIsReproducedWithItsDriversAtOne) {
  EXPECT_LE(MaxDistance(Solve(rig(), {1.0, 1.0}), LoadMesh(Cylinder("poses-2_cylinder-4.obj")).vertices), Tolerance());
}

TEST(RigMasks, AllZeroMaskIsTheRestShapeAndAllOneMaskIsNoMask) {
  TempDir dir;
  const auto build = [&](const nlohmann::json& mask, const std::string& name) {
    nlohmann::json rig = {{"rest", Cylinder("cylinder.obj")},
                          {"targets", {{{"name", "twist"}, {"mesh", Cylinder("poses-2_cylinder-3.obj")}}}}};
    if (!mask.is_null()) rig["targets"][0]["mask"] = mask;
    return BuildRig(LoadRigFile(WriteRig(dir, rig, name)), testing::NoPathsRigOptions());
  };
  const Points rest = LoadMesh(Cylinder("cylinder.obj")).vertices;
  const double tolerance = 1e-6 * BoundingBoxDiagonal(rest);
  const auto zero = build(std::vector<double>(420, 0.0), "zero.json");
  EXPECT_LE(MaxDistance(Solve(zero, {1.0}), rest), tolerance);
  EXPECT_LE(MaxDistance(Solve(zero, {0.6}), rest), tolerance);
  const auto one = build(std::vector<double>(420, 1.0), "one.json");
  const auto none = build(nullptr, "none.json");
  for (double w : {0.6, 1.0}) {
    EXPECT_LE(MaxDistance(Solve(one, {w}), Solve(none, {w})), tolerance) << "weight " << w;
  }
}

// The face (6706 vertices, an open shell) with jawOpen and an in-between sculpted here (the linear midpoint pushed
// forward a little); no target paths, so the build takes seconds: the sculpts are still reproduced exactly.
TEST(RigFace, InbetweenTargetAndAllZeroMaskOnTheFace) {
  TempDir dir;
  const TriangleMesh rest = LoadMesh(DataPath("face/generic_neutral_mesh.obj"));
  const TriangleMesh open = LoadMesh(DataPath("face/jawOpen.obj"));
  Points half = (rest.vertices + open.vertices) / 2;
  half.col(2) += 0.02 * (open.vertices - rest.vertices).rowwise().norm();
  WriteObj(dir.File("half.obj"), half, rest.faces);
  RigOptions options;
  options.target_paths = false;
  const auto rig_of = [&](const nlohmann::json& target) {
    const nlohmann::json rig = {{"rest", DataPath("face/generic_neutral_mesh.obj")}, {"targets", {target}}};
    return BuildRig(LoadRigFile(WriteRig(dir, rig)), options);
  };
  const double tolerance = 1e-6 * BoundingBoxDiagonal(rest.vertices);
  const auto rig = rig_of({{"name", "jawOpen"},
                           {"mesh", DataPath("face/jawOpen.obj")},
                           {"inbetweens", {{{"weight", 0.5}, {"mesh", dir.File("half.obj")}}}}});
  // Read back as float32, as every mesh file is.
  EXPECT_LE(MaxDistance(Solve(rig, {0.5}), LoadMesh(dir.File("half.obj")).vertices), tolerance);
  EXPECT_LE(MaxDistance(Solve(rig, {1.0}), open.vertices), tolerance);
  const auto off = rig_of({{"name", "jawOpen"},
                           {"mesh", DataPath("face/jawOpen.obj")},
                           {"mask", std::vector<double>(static_cast<size_t>(rest.vertices.rows()), 0.0)}});
  EXPECT_LE(MaxDistance(Solve(off, {1.0}), rest.vertices), tolerance);
}

}  // namespace
}  // namespace springblend::cli
