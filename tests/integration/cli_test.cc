// The `springblend blend` command as users and scripts call it: a real process, its JSON lines, its
// files and its exit codes.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <fmt/format.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "integration/cli_process.h"
#include "springblend/point_cache.h"
#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;
using testing::CliRun;
using testing::DataPath;
using testing::RunCli;
using testing::TempDir;

const std::string kRest = DataPath("cylinder/cylinder.obj");
const std::string kBend = DataPath("cylinder/poses-2_cylinder-1.obj");
const std::string kTwist = DataPath("cylinder/poses-2_cylinder-3.obj");

TEST(CliBlend, SolvesOneFrameAndPrintsItsSummary) {
  TempDir dir;
  const CliRun run = RunCli("blend --rest " + kRest + " --target " + kBend + " --target " + kTwist +
                             " --weights 0.5,0.25 --out " + dir.File("out.obj"),
                         dir);
  ASSERT_EQ(run.exit_code, 0) << run.stderr_text;
  ASSERT_EQ(run.lines.size(), 1u);
  const auto& j = run.lines[0];
  EXPECT_GT(j["vertices"].get<int>(), 420);  // the mesh, two hole caps and the interior
  EXPECT_GT(j["springs"].get<int>(), 2400);
  EXPECT_EQ(j["converged"], true);
  EXPECT_GT(j["newton_iterations"].get<int>(), 0);
  EXPECT_LE(j["residual"].get<double>(), 1e-6);  // SolveOptions' default tolerance
  EXPECT_GT(j["solve_ms"].get<double>(), 0.0);
  const TriangleMesh out = LoadMesh(dir.File("out.obj"));
  EXPECT_EQ(out.vertices.rows(), 420);
  EXPECT_EQ(out.faces, LoadMesh(kRest).faces);
}

TEST(CliBlend, SweepWritesOneMeshAndOneLinePerFrameEndingOnTheTarget) {
  TempDir dir;
  const CliRun run = RunCli("blend --rest " + kRest + " --target " + kBend + " --sweep 6 --out " +
                             dir.File("sweep"),
                         dir);
  ASSERT_EQ(run.exit_code, 0) << run.stderr_text;
  ASSERT_EQ(run.lines.size(), 6u);
  for (int i = 0; i < 6; ++i) {
    EXPECT_EQ(run.lines[i]["frame"], i);
    EXPECT_NEAR(run.lines[i]["weights"][0].get<double>(), i / 5.0, 1e-15);
    EXPECT_TRUE(std::filesystem::exists(dir.File("sweep/frame_000" + std::to_string(i) + ".obj")));
  }
  const TriangleMesh last = LoadMesh(dir.File("sweep/frame_0005.obj"));
  const TriangleMesh target = LoadMesh(kBend);
  EXPECT_LE(testing::MaxDistance(last.vertices, target.vertices),
            1e-6 * BoundingBoxDiagonal(target.vertices));
}

TEST(CliBlend, PointCacheOutputHoldsTheSameFramesAsTheObjFiles) {
  TempDir dir;
  const std::string args = "blend --rest " + kRest + " --target " + kBend + " --target " + kTwist +
                           " --weights 0.9,0.4 --sweep 4 --collider sphere:-1.7,0.75,0.75,0.35 --out ";
  const CliRun objs = RunCli(args + dir.File("objs"), dir);
  ASSERT_EQ(objs.exit_code, 0) << objs.stderr_text;
  const CliRun cache = RunCli(args + dir.File("shot.pc2"), dir);
  ASSERT_EQ(cache.exit_code, 0) << cache.stderr_text;
  ASSERT_EQ(cache.lines.size(), 4u);  // the JSON lines stay
  EXPECT_FALSE(std::filesystem::exists(dir.File("shot.pc2.partial")));
  const PointCache read = ReadPointCache(dir.File("shot.pc2"));
  EXPECT_EQ(read.start_frame, 1.0f);  // frame = index + 1
  EXPECT_EQ(read.sample_rate, 1.0f);
  ASSERT_EQ(read.samples.size(), 4u);
  for (int i = 0; i < 4; ++i) {
    const Points obj = LoadMesh(dir.File("objs/frame_000" + std::to_string(i) + ".obj")).vertices;
    // Both are the solve rounded to float32 (OBJ text is printed from the doubles and parsed as float32).
    EXPECT_LE(testing::MaxDistance(read.samples[i], obj), 1e-6 * BoundingBoxDiagonal(obj)) << "frame " << i;
  }
  EXPECT_GT(testing::MaxDistance(read.samples[3], read.samples[0]), 0.1);
  // One frame into a cache works too; a cache in a missing directory is the caller's mistake (exit 2).
  EXPECT_EQ(RunCli("blend --rest " + kRest + " --target " + kBend + " --weights 0.5 --out " + dir.File("one.pc2"), dir)
                .exit_code,
            0);
  EXPECT_EQ(ReadPointCache(dir.File("one.pc2")).samples.size(), 1u);
  const CliRun nowhere =
      RunCli("blend --rest " + kRest + " --target " + kBend + " --sweep 2 --out " + dir.File("no/dir/x.pc2"), dir);
  EXPECT_EQ(nowhere.exit_code, 2);
  EXPECT_THAT(nowhere.stderr_text, HasSubstr("no/dir/x.pc2"));
}

TEST(CliBlend, LinearFlagWritesTheLinearBlendshape) {
  TempDir dir;
  const CliRun run = RunCli("blend --rest " + kRest + " --target " + kBend + " --weights 0.5 --linear --out " +
                             dir.File("lin.obj"),
                         dir);
  ASSERT_EQ(run.exit_code, 0) << run.stderr_text;
  EXPECT_EQ(run.lines[0]["termination"], "linear");
  const Points expected = 0.5 * (LoadMesh(kRest).vertices + LoadMesh(kBend).vertices);
  // OBJ text read back through OpenMesh's float32 parser.
  EXPECT_LE(testing::MaxDistance(LoadMesh(dir.File("lin.obj")).vertices, expected),
            1e-7 * BoundingBoxDiagonal(expected));
}

TEST(CliBlend, ColliderAndPinKeepTheSweepOutOfTheBallAndOnThePin) {
  TempDir dir;
  const CliRun run = RunCli("blend --rest " + kRest + " --target " + kBend +
                                " --sweep 6 --collider sphere:-1.7,0.75,0.75,0.35 --pin 0:2,0.475529,-0.154509 --out " +
                                dir.File("scene"),
                            dir);
  ASSERT_EQ(run.exit_code, 0) << run.stderr_text;
  ASSERT_EQ(run.lines.size(), 6u);
  int contacts = 0;
  for (const auto& j : run.lines) {
    EXPECT_EQ(j["pins"], 1);
    contacts += j["contacts"].get<int>();
  }
  EXPECT_GT(contacts, 0);
  for (int i = 0; i < 6; ++i) {
    const TriangleMesh frame = LoadMesh(dir.File("scene/frame_000" + std::to_string(i) + ".obj"));
    for (Eigen::Index v = 0; v < frame.vertices.rows(); ++v) {
      EXPECT_GE((frame.vertices.row(v) - Eigen::RowVector3d(-1.7, 0.75, 0.75)).norm(), 0.35 - 1e-5);
    }
  }
}

TEST(CliBlend, FramesFileAnimatesWeightsObstaclesAndPins) {
  TempDir dir;
  const std::string scene = dir.Write("scene.json", R"({
    "colliders": ["sphere:-1.7,0.75,5.75,0.35"],
    "frames": [
      {"weights": [0.5], "colliders": [{"translation": [0, 0, 0]}]},
      {"weights": [0.8], "colliders": [{"translation": [0, 0, -5]}]},
      {"weights": [0.8], "colliders": [{"translation": [0, 0, 0], "rotation": [1, 0, 0, 0]}],
       "pins": [{"vertex": 5, "position": [2, 0, 0]}]}
    ]})");
  const CliRun run = RunCli("blend --rest " + kRest + " --target " + kBend + " --frames " + scene + " --out " +
                                dir.File("out"),
                            dir);
  ASSERT_EQ(run.exit_code, 0) << run.stderr_text;
  ASSERT_EQ(run.lines.size(), 3u);
  EXPECT_EQ(run.lines[0]["contacts"], 0);   // the ball is far away
  EXPECT_GT(run.lines[1]["contacts"].get<int>(), 0);  // moved into the bend's path
  EXPECT_EQ(run.lines[2]["contacts"], 0);   // and away again: contacts release
  EXPECT_EQ(run.lines[2]["pins"], 1);
  EXPECT_TRUE(std::filesystem::exists(dir.File("out/frame_0002.obj")));
}

TEST(CliBlend, ABadFrameAnywhereInTheFileIsRefusedBeforeAnythingIsWritten) {
  TempDir dir;
  const std::string scene = dir.Write("scene.json", R"({"frames": [{"weights": [0.5]}, {"weights": [0.5, 0.2]}]})");
  const CliRun run = RunCli("blend --rest " + kRest + " --target " + kBend + " --frames " + scene + " --out " +
                                dir.File("out"),
                            dir);
  EXPECT_EQ(run.exit_code, 2);
  EXPECT_THAT(run.stderr_text, HasSubstr("frames[1]: weights has 2 entries"));
  EXPECT_FALSE(std::filesystem::exists(dir.File("out/frame_0000.obj")));
}

// Weights by target name (the mesh file's name; the others 0) give the same frame as positional ones, in
// --weights and in a frames file; unknown names and badly typed fields are refused naming the field.
TEST(CliBlend, WeightsByNameAreTheTargetsOwnAndBadFieldsAreNamed) {
  TempDir dir;
  const std::string rig = "blend --rest " + kRest + " --target " + kBend + " --target " + kTwist;
  const CliRun positional = RunCli(rig + " --weights 0.9,0.4 --out " + dir.File("positional.obj"), dir);
  ASSERT_EQ(positional.exit_code, 0) << positional.stderr_text;
  const CliRun named =
      RunCli(rig + " --weights poses-2_cylinder-3=0.4,poses-2_cylinder-1=0.9 --out " + dir.File("named.obj"), dir);
  ASSERT_EQ(named.exit_code, 0) << named.stderr_text;
  EXPECT_EQ(named.lines.at(0)["weights"], positional.lines.at(0)["weights"]);
  EXPECT_EQ(testing::MaxDistance(LoadMesh(dir.File("named.obj")).vertices, LoadMesh(dir.File("positional.obj")).vertices),
            0.0);
  const std::string scene = dir.Write("named.json", R"({"frames": [{"weights": {"poses-2_cylinder-1": 0.9,
                                                                              "poses-2_cylinder-3": 0.4}},
                                                                 {"weights": {"poses-2_cylinder-3": 0.4}}]})");
  const CliRun frames = RunCli(rig + " --frames " + scene + " --out " + dir.File("frames"), dir);
  ASSERT_EQ(frames.exit_code, 0) << frames.stderr_text;
  ASSERT_EQ(frames.lines.size(), 2u);
  EXPECT_EQ(frames.lines[0]["weights"], positional.lines.at(0)["weights"]);
  EXPECT_EQ(frames.lines[1]["weights"], nlohmann::json::array({0.0, 0.4}));  // the target not named is at 0
  EXPECT_EQ(testing::MaxDistance(LoadMesh(dir.File("frames/frame_0000.obj")).vertices,
                                 LoadMesh(dir.File("positional.obj")).vertices),
            0.0);

  const CliRun unknown = RunCli(rig + " --weights jawOpen=1 --out " + dir.File("x.obj"), dir);
  EXPECT_EQ(unknown.exit_code, 2);
  EXPECT_THAT(unknown.stderr_text,
              HasSubstr("--weights: 'jawOpen' is not a target of this character (targets: poses-2_cylinder-1, "
                        "poses-2_cylinder-3)"));
  const CliRun mixed = RunCli(rig + " --weights poses-2_cylinder-1=1,0.5 --out " + dir.File("x.obj"), dir);
  EXPECT_EQ(mixed.exit_code, 2);
  EXPECT_THAT(mixed.stderr_text, HasSubstr("by name (NAME=W,...) or none"));
  const std::string typo = dir.Write("typo.json", R"({"frames": [{"weights": [0.5, 0.1]},
                                                               {"weights": {"poses-2_cylinder-1": "0.5"}}]})");
  const CliRun typed = RunCli(rig + " --frames " + typo + " --out " + dir.File("typo"), dir);
  EXPECT_EQ(typed.exit_code, 2);
  EXPECT_THAT(typed.stderr_text, HasSubstr(typo + ": frames[1].weights.poses-2_cylinder-1 must be a number, not string"));
  const std::string wrong = dir.Write("wrong.json", R"({"frames": [{"weights": {"nope": 0.5}}]})");
  const CliRun refused = RunCli(rig + " --frames " + wrong + " --out " + dir.File("wrong"), dir);
  EXPECT_EQ(refused.exit_code, 2);
  EXPECT_THAT(refused.stderr_text, HasSubstr(wrong + ": frames[0].weights: 'nope' is not a target"));
  const std::string pins = dir.Write("pins.json", R"({"frames": [{"weights": [0.5, 0], "pins": [{"vertex": 3,
                                                                  "position": [1, "2", 3]}]}]})");
  const CliRun pin = RunCli(rig + " --frames " + pins + " --out " + dir.File("pins"), dir);
  EXPECT_EQ(pin.exit_code, 2);
  EXPECT_THAT(pin.stderr_text, HasSubstr("frames[0].pins[0].position[1] must be a number"));
  EXPECT_FALSE(std::filesystem::exists(dir.File("pins/frame_0000.obj")));
}

// A request's mistakes are refused before the rig's physics is built: on the bundled face, whose target path
// alone takes about a minute to build (several under the sanitizers), a misspelt weight, a bad scene file and a
// bad collider come back at once with exit code 2 and nothing written. (A liveness bound, not a timing: the
// refusals take well under a second; the build they skip, a minute or more.)
TEST(CliRefusals, MistakesAreRefusedBeforeThePhysicsIsBuilt) {
  TempDir dir;
  const std::string face = "blend --rest " + DataPath("face/generic_neutral_mesh.obj") + " --target " +
                           DataPath("face/jawOpen.obj");
  const std::string scene = dir.Write("scene.json", R"({"frames": [{"weights": {"jawOpen": 0.5}},
                                                                  {"weights": {"jawopen": 0.5}}]})");
  const std::vector<std::pair<std::string, std::string>> cases = {
      {" --weights jawOpne=1", "'jawOpne' is not a target of this character (targets: jawOpen)"},
      {" --frames " + scene, "frames[1].weights: 'jawopen' is not a target"},
      {" --weights 1 --collider sphere:0,0,0,-1", "radius"},
      {" --weights 1e300", "beyond"},
  };
  for (const auto& [arguments, message] : cases) {
    const auto start = std::chrono::steady_clock::now();
    const CliRun run = RunCli(face + arguments + " --out " + dir.File("out"), dir);
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    EXPECT_EQ(run.exit_code, 2) << arguments << ": " << run.stderr_text;
    EXPECT_THAT(run.stderr_text, HasSubstr(message)) << arguments;
    EXPECT_LT(seconds, 30.0) << arguments << ": the refusal waited for the physics";
    EXPECT_FALSE(std::filesystem::exists(dir.File("out"))) << arguments;
  }
}

// bake-rig writes a rig file that `blend --linear` plays back: with both targets at 1 (the rig's combination) it
// gives the solved frame, and with --solved-inbetweens also at a baked in-between's weight; between in-betweens
// it is nearer the solved frame than the original rig's linear blendshape, and fitted in-betweens (the default)
// nearer the samples than solved ones. Bad pair lists are refused by name.
TEST(CliBakeRig, ABakedRigPlaysThePhysicsBackAsAPlainBlendshapeRig) {
  TempDir dir;
  const std::string rig = DataPath("cylinder/rig.json");
  const std::string options = "bake-rig --rig " + rig + " --samples 16 --inbetweens 3";
  const CliRun bake = RunCli(options + " --out " + dir.File("baked"), dir);
  ASSERT_EQ(bake.exit_code, 0) << bake.stderr_text;
  ASSERT_EQ(bake.lines.size(), 1u);
  const CliRun on_path = RunCli(options + " --solved-inbetweens --out " + dir.File("solved"), dir);
  ASSERT_EQ(on_path.exit_code, 0) << on_path.stderr_text;
  ASSERT_EQ(on_path.lines.size(), 1u);
  const nlohmann::json& summary = bake.lines[0];
  ASSERT_EQ(summary["targets"].size(), 2u);
  EXPECT_EQ(summary["targets"][0]["inbetweens"].size(), 3u);
  EXPECT_EQ(summary["combinations"][0]["name"], "bend_twist");
  EXPECT_EQ(summary["inbetweens"], "fitted");
  EXPECT_EQ(summary["snaps"], 0);  // the cylinder's paths are smooth
  EXPECT_EQ(summary["targets"][0]["snaps"], 0);
  EXPECT_EQ(on_path.lines[0]["inbetweens"], "solved");
  EXPECT_LT(summary["max_error"].get<double>(), summary["linear_max_error"].get<double>());
  EXPECT_LE(summary["max_error"].get<double>(), on_path.lines[0]["max_error"].get<double>());
  const double diagonal = BoundingBoxDiagonal(LoadMesh(DataPath("cylinder/cylinder.obj")).vertices);
  const std::string baked = " --rig " + dir.File("baked/rig.json") + " --linear";
  const auto frame = [&](const std::string& how, const std::string& weights, const std::string& name) {
    const CliRun run = RunCli("blend" + how + " --weights " + weights + " --out " + dir.File(name), dir);
    EXPECT_EQ(run.exit_code, 0) << run.stderr_text;
    return LoadMesh(dir.File(name)).vertices;
  };
  const double at = on_path.lines[0]["targets"][0]["inbetweens"][1].get<double>();
  const std::string w = fmt::format("bend={}", at);
  // float32 OBJ text on both sides.
  EXPECT_LE(testing::MaxDistance(frame(" --linear --rig " + dir.File("solved/rig.json"), w, "b1.obj"),
                                 frame(" --rig " + rig, w, "s1.obj")),
            1e-6 * diagonal);
  EXPECT_LE(testing::MaxDistance(frame(baked, "1,1", "b2.obj"), frame(" --rig " + rig, "1,1", "s2.obj")),
            1e-6 * diagonal);
  const Points solved = frame(" --rig " + rig, "0.4,0.3", "s3.obj");
  EXPECT_LT(testing::MaxDistance(frame(baked, "0.4,0.3", "b3.obj"), solved),
            testing::MaxDistance(frame(" --linear --rig " + rig, "0.4,0.3", "l3.obj"), solved));

  const CliRun bad = RunCli("bake-rig --rig " + rig + " --pairs bend*twirl --out " + dir.File("bad"), dir);
  EXPECT_EQ(bad.exit_code, 2);
  EXPECT_THAT(bad.stderr_text, ::testing::HasSubstr("pair 'twirl': not a target of this rig (targets: bend, twist)"));
  const CliRun syntax = RunCli("bake-rig --rig " + rig + " --pairs bend+twist --out " + dir.File("bad"), dir);
  EXPECT_EQ(syntax.exit_code, 2);
  EXPECT_THAT(syntax.stderr_text, ::testing::HasSubstr("--pairs: 'bend+twist' is not A*B"));
}

// A point cache placed on a shot's timeline: --start-frame and --sample-rate go into its header; they are
// refused for OBJ output, which has no timeline.
TEST(CliBlend, PointCacheStartsAtTheShotsFirstFrame) {
  TempDir dir;
  const std::string args = "blend --rest " + kRest + " --target " + kBend + " --sweep 3 --start-frame 1001 ";
  const CliRun run = RunCli(args + "--sample-rate 0.5 --out " + dir.File("shot.pc2"), dir);
  ASSERT_EQ(run.exit_code, 0) << run.stderr_text;
  const PointCache read = ReadPointCache(dir.File("shot.pc2"));
  EXPECT_EQ(read.start_frame, 1001.0f);
  EXPECT_EQ(read.sample_rate, 0.5f);
  EXPECT_EQ(read.samples.size(), 3u);
  const CliRun objs = RunCli(args + "--out " + dir.File("objs"), dir);
  EXPECT_EQ(objs.exit_code, 2);
  EXPECT_THAT(objs.stderr_text, HasSubstr("is not a .pc2 file"));
  EXPECT_EQ(RunCli(args + "--sample-rate 0 --out " + dir.File("zero.pc2"), dir).exit_code, 2);
}

std::string FileBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

// A captured take (issue 59) on the bundled face: the CLI's point cache of a --linear solve of the excerpt is the
// very file the same frames give as a scene file, to the bit. The expected frames are read here with a plain
// split of the CSV (ARKit's JawOpen is ICT's jawOpen, MouthSmileLeft its mouthSmile_L), and the cache starts at
// the take's first timecode, 16:56:29:40 at 60 per second stepping by 2: a 30 fps take.
TEST(CliTake, ALinearSolveOfATakeIsItsFramesGivenAsASceneFileToTheBit) {
  TempDir dir;
  const std::string take = DataPath("take/alex_rom_4_excerpt.csv");
  const std::vector<std::pair<std::string, std::string>> names = {{"jawOpen", "JawOpen"},
                                                                  {"mouthClose", "MouthClose"},
                                                                  {"mouthFunnel", "MouthFunnel"},
                                                                  {"mouthSmile_L", "MouthSmileLeft"},
                                                                  {"mouthStretch_L", "MouthStretchLeft"}};
  std::string face = "blend --linear --rest " + DataPath("face/generic_neutral_mesh.obj");
  for (const auto& [target, shape] : names) face += " --target " + DataPath("face/" + target + ".obj");
  std::ifstream csv(take);
  std::string line;
  std::getline(csv, line);
  std::vector<std::string> header;
  for (std::stringstream fields(line); std::getline(fields, line, ',');) header.push_back(line);
  nlohmann::json frames = nlohmann::json::array();
  std::string first_timecode;
  while (std::getline(csv, line)) {
    std::vector<std::string> row;
    for (std::stringstream fields(line); std::getline(fields, line, ',');) row.push_back(line);
    if (first_timecode.empty()) first_timecode = row[0];
    nlohmann::json weights;
    for (const auto& [target, shape] : names) {
      const size_t column = std::find(header.begin(), header.end(), shape) - header.begin();
      weights[target] = std::stod(row.at(column));
    }
    frames.push_back({{"weights", weights}});
  }
  ASSERT_EQ(frames.size(), 40u);
  ASSERT_EQ(first_timecode.substr(0, 11), "16:56:29:40");
  std::ofstream(dir.File("scene.json")) << nlohmann::json({{"frames", frames}}).dump();
  const double start = ((16 * 3600 + 56 * 60 + 29) * 60 + 40) / 2.0;

  const CliRun from_take = RunCli(face + " --take " + take + " --out " + dir.File("take.pc2"), dir);
  ASSERT_EQ(from_take.exit_code, 0) << from_take.stderr_text;
  EXPECT_EQ(from_take.lines.size(), 40u);
  // The report, once: rotations left out, shapes this face lacks.
  EXPECT_THAT(from_take.stderr_text, HasSubstr("alex_rom_4_excerpt.csv: 40 rows, 40 frames; 30 frames per second "
                                               "(timecode at 60 per second, step 2), first frame 1829690\n"));
  EXPECT_THAT(from_take.stderr_text, HasSubstr("not weights, left out: HeadYaw, HeadPitch"));
  EXPECT_THAT(from_take.stderr_text, HasSubstr("shapes that drive no target: EyeBlinkLeft"));
  const CliRun from_scene = RunCli(face + fmt::format(" --frames {} --start-frame {} --out {}", dir.File("scene.json"),
                                                      start, dir.File("scene.pc2")),
                                   dir);
  ASSERT_EQ(from_scene.exit_code, 0) << from_scene.stderr_text;
  const std::string bytes = FileBytes(dir.File("take.pc2"));
  ASSERT_EQ(bytes.size(), 32u + 40u * 6706u * 12u);
  EXPECT_TRUE(bytes == FileBytes(dir.File("scene.pc2")));
  EXPECT_EQ(ReadPointCache(dir.File("take.pc2")).start_frame, static_cast<float>(start));
  // --frames recognises the take by its header; --start-frame and --sample-rate given win over the timecode.
  const CliRun by_header = RunCli(face + " --frames " + take + " --out " + dir.File("header.pc2"), dir);
  ASSERT_EQ(by_header.exit_code, 0) << by_header.stderr_text;
  EXPECT_TRUE(FileBytes(dir.File("header.pc2")) == bytes);
  const CliRun placed =
      RunCli(face + " --take " + take + " --start-frame 1001 --sample-rate 2 --out " + dir.File("placed.pc2"), dir);
  ASSERT_EQ(placed.exit_code, 0) << placed.stderr_text;
  const PointCache cache = ReadPointCache(dir.File("placed.pc2"));
  EXPECT_EQ(std::make_pair(cache.start_frame, cache.sample_rate), std::make_pair(1001.0f, 2.0f));
}

// Bad takes are refused with exit code 2, the file, line and column named, and nothing written.
TEST(CliTake, BadTakesAreRefusedNamingTheLineAndColumn) {
  TempDir dir;
  const std::string face = "blend --linear --rest " + DataPath("face/generic_neutral_mesh.obj") + " --target " +
                           DataPath("face/jawOpen.obj");
  const auto refused = [&](const std::string& text, const std::string& message, const std::string& extra = "") {
    std::ofstream(dir.File("bad.csv")) << text;
    const CliRun run = RunCli(face + " --take " + dir.File("bad.csv") + extra + " --out " + dir.File("out.pc2"), dir);
    EXPECT_EQ(run.exit_code, 2) << text;
    EXPECT_THAT(run.stderr_text, HasSubstr(message));
    EXPECT_FALSE(std::filesystem::exists(dir.File("out.pc2")) || std::filesystem::exists(dir.File("out.pc2.partial")));
  };
  const std::string header = "Timecode,BlendShapeCount,JawOpen,HeadYaw\n00:00:00:00,2,0.5,0\n";
  refused(header + "00:00:00:01,2,0.5\n", "bad.csv: line 3, column 4: the row ends after 3 of the header's 4 columns");
  refused(header + "00:00:00:01,2,x,0\n", "bad.csv: line 3, column 3: (JawOpen) 'x' is not a number");
  refused("Timecode,BlendShapeCount,TongueOut\n00:00:00:00,1,0.5\n",
          "bad.csv: line 1: no column of the header is a shape of this rig");
  refused(header, "--lost", " --lost drop");
  // A lost-tracking row is no error; --map and --lost without a take are.
  refused(header + "00:00:00:01,0\n00:00:00:02,2,2000,0\n", "bad.csv line 4: ");
  const CliRun map_alone = RunCli(face + " --weights 0.5 --map m.json --out " + dir.File("one.obj"), dir);
  EXPECT_EQ(map_alone.exit_code, 2);
  EXPECT_THAT(map_alone.stderr_text, HasSubstr("--map and --lost go with a take"));
}

// Targets that move every vertex leave a rig without an anchor floating: colliders are refused, and the
// rig summary (-v) says how to hold it. Holding the open cylinder's outer rim (one end's loop) holds it, and the
// collider then works.
TEST(CliBlend, AHeldOuterRimHoldsARigWhoseTargetsMoveEveryVertex) {
  TempDir dir;
  const std::string args = "blend --rest " + kRest + " --target " + DataPath("cylinder/poses-1_cylinder-2.obj") +
                           " --no-anchor --weights 1 --collider sphere:0,0.75,0.75,0.3 -v --out ";
  const CliRun floating = RunCli(args + dir.File("floating.obj"), dir);
  EXPECT_EQ(floating.exit_code, 2);
  EXPECT_THAT(floating.stderr_text, HasSubstr("the rig is floating"));
  EXPECT_THAT(floating.stderr_text, HasSubstr("--hold-outer-rim"));
  const CliRun held = RunCli(args + dir.File("held.obj") + " --hold-outer-rim", dir);
  ASSERT_EQ(held.exit_code, 0) << held.stderr_text;
  EXPECT_THAT(held.stderr_text, HasSubstr("outer rim"));
  EXPECT_THAT(held.stderr_text, Not(HasSubstr("the rig is floating")));
  EXPECT_TRUE(held.lines.at(0)["converged"].get<bool>());
}

struct BadCall {
  const char* name;
  std::string arguments;
  std::vector<std::string> message_parts;
};

// Readable in ctest's output (gtest prints a parameter without PrintTo as raw bytes).
void PrintTo(const BadCall& c, std::ostream* os) { *os << std::string(c.name) + ": springblend " + c.arguments; }

class CliRefuses : public ::testing::TestWithParam<BadCall> {};

TEST_P(CliRefuses, WithExitCodeTwoAndAMessageNamingTheProblem) {
  TempDir dir;
  const CliRun run = RunCli(GetParam().arguments + " --out " + dir.File("x.obj"), dir);
  EXPECT_EQ(run.exit_code, 2) << run.stderr_text;
  EXPECT_TRUE(run.lines.empty());
  for (const auto& part : GetParam().message_parts) EXPECT_THAT(run.stderr_text, HasSubstr(part));
  EXPECT_FALSE(std::filesystem::exists(dir.File("x.obj")));
}

INSTANTIATE_TEST_SUITE_P(
    BadInput, CliRefuses,
    ::testing::Values(
        BadCall{"MissingRest", "blend --rest /nope/rest.obj --target " + kBend, {"/nope/rest.obj", "not found"}},
        BadCall{"MismatchedTarget",
                "blend --rest " + kRest + " --target " + DataPath("cube/poses-1_cube-1.obj"),
                {"poses-1_cube-1.obj", "1538 vertices", "420"}},
        BadCall{"WrongWeightCount",
                "blend --rest " + kRest + " --target " + kBend + " --target " + kTwist + " --weights 0.5",
                {"weights has 1 entries but the rig has 2 targets"}},
        BadCall{"NanWeight", "blend --rest " + kRest + " --target " + kBend + " --weights nan",
                {"weights[0]", "not finite"}},
        BadCall{"FixedOutOfRange", "blend --rest " + kRest + " --target " + kBend + " --fixed 3,5000",
                {"fixed_vertices[1] = 5000"}},
        BadCall{"UnknownSolver", "blend --rest " + kRest + " --target " + kBend + " --solver magic",
                {"unknown linear solver 'magic'"}},
        BadCall{"MissingTarget", "blend --rest " + kRest, {"--target"}},
        BadCall{"BadCollider", "blend --rest " + kRest + " --target " + kBend + " --collider sphere:1,2",
                {"sphere takes 4 numbers"}},
        BadCall{"BadPin", "blend --rest " + kRest + " --target " + kBend + " --pin 3:1,2", {"--pin '3:1,2'"}},
        BadCall{"PinOutOfRange", "blend --rest " + kRest + " --target " + kBend + " --pin 99999:1,2,3",
                {"pins[0].vertex = 99999"}},
        BadCall{"MissingFramesFile", "blend --rest " + kRest + " --target " + kBend + " --frames /nope.json",
                {"frames file not found: /nope.json"}}),
    [](const ::testing::TestParamInfo<BadCall>& param) { return std::string(param.param.name); });

}  // namespace
}  // namespace springblend
