// `springblend bake-rig`: bake a rig's physics into a plain blendshape rig (in-betweens and combination
// correctives, solver/include/springblend/bake.h), from frames solved locally or by a server, and write it as a
// rig file with its meshes.
#include <fmt/format.h>

#include <algorithm>
#include <cctype>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "commands.h"
#include "remote_call.h"
#include "rig_file.h"
#include "springblend/bake.h"
#include "springblend/client.h"
#include "springblend/error.h"
#include "springblend/mesh.h"
#include "springblend/rig.h"
#include "springblend/solve.h"

namespace springblend::cli {
namespace {

struct BakeArgs {
  std::string rig, rest, out;
  std::vector<std::string> targets;
  std::vector<int> fixed;
  bool hold_outer_rim = false;
  int inbetweens = BakeOptions{}.inbetweens;
  double tolerance = 0.0;
  int samples = BakeOptions{}.samples;
  bool solved_inbetweens = false;
  std::string pairs = "auto";
  double pair_threshold = BakeOptions{}.pair_threshold;
  // Against a server: its character (the frames are solved there; the rest mesh's faces come from it).
  Connection connection;
  std::string character;
};

// A file name for a target's mesh: its index, then its name with anything but letters, digits, '-' and '_'
// replaced (names are free text; two may differ only in such characters).
std::string MeshName(const std::string& prefix, size_t index, const std::string& name, const std::string& suffix) {
  std::string safe;
  for (char c : name) safe += std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_' ? c : '_';
  return fmt::format("{}{:02}_{}{}.obj", prefix, index, safe.substr(0, 64), suffix);
}

// DIR/rig.json and its meshes: the rest shape, each target at 1 with its in-betweens, each combination.
void WriteBakedRig(const BakedRig& baked, const Faces& faces, const std::string& dir) {
  std::filesystem::create_directories(dir);
  const std::filesystem::path root(dir);
  nlohmann::json targets = nlohmann::json::array();
  WriteObj((root / "rest.obj").string(), baked.rest, faces);
  for (size_t t = 0; t < baked.targets.size(); ++t) {
    const BakedTarget& target = baked.targets[t];
    nlohmann::json entry = {{"name", target.name}, {"mesh", MeshName("t", t, target.name, "")}};
    WriteObj((root / entry["mesh"].get<std::string>()).string(), target.full, faces);
    if (!target.inbetweens.empty()) {
      nlohmann::json inbetweens = nlohmann::json::array();
      for (size_t k = 0; k < target.inbetweens.size(); ++k) {
        const std::string mesh = MeshName("t", t, target.name, fmt::format("_inbetween{}", k));
        WriteObj((root / mesh).string(), target.inbetweens[k].positions, faces);
        inbetweens.push_back({{"weight", target.inbetweens[k].weight}, {"mesh", mesh}});
      }
      entry["inbetweens"] = std::move(inbetweens);
    }
    targets.push_back(std::move(entry));
  }
  for (size_t c = 0; c < baked.combinations.size(); ++c) {
    const BakedCombination& combination = baked.combinations[c];
    std::vector<std::string> drivers;
    for (int d : combination.drivers) drivers.push_back(baked.targets[d].name);
    // A pair the bake found may share its name with a target: keep every name unique.
    std::string name = combination.name;
    const auto taken = [&](const std::string& n) {
      for (const auto& t : targets) {
        if (t["name"] == n) return true;
      }
      return false;
    };
    while (taken(name)) name += "_";
    const std::string mesh = MeshName("c", c, name, "");
    WriteObj((root / mesh).string(), combination.shape, faces);
    targets.push_back({{"name", name}, {"mesh", mesh}, {"combination", drivers}});
  }
  const nlohmann::json rig = {{"rest", "rest.obj"}, {"targets", std::move(targets)}};
  std::ofstream file(root / "rig.json");
  file << rig.dump(1) << "\n";
  if (!file) throw Error(ErrorCode::kInvalidInput, fmt::format("{}: cannot write rig.json", dir));
}

BakeOptions OptionsOf(const BakeArgs& args) {
  BakeOptions options;
  options.inbetweens = args.inbetweens;
  options.tolerance = args.tolerance;
  options.samples = args.samples;
  options.solved_inbetweens = args.solved_inbetweens;
  options.pair_threshold = args.pair_threshold;
  if (args.pairs == "auto") {
    options.pair_mode = BakePairs::kAuto;
  } else if (args.pairs == "none") {
    options.pair_mode = BakePairs::kNone;
  } else {
    options.pair_mode = BakePairs::kList;
    std::string rest = args.pairs;
    while (!rest.empty()) {
      const size_t comma = rest.find(',');
      const std::string item = rest.substr(0, comma);
      rest = comma == std::string::npos ? "" : rest.substr(comma + 1);
      const size_t star = item.find('*');
      if (star == std::string::npos || star == 0 || star + 1 == item.size() ||
          item.find('*', star + 1) != std::string::npos) {
        throw Error(ErrorCode::kInvalidInput,
                    fmt::format("--pairs: '{}' is not A*B (give auto, none or A*B,C*D with target names)", item));
      }
      options.pairs.emplace_back(item.substr(0, star), item.substr(star + 1));
    }
  }
  options.progress = [](const std::string& stage, int done, int total) {
    std::cerr << fmt::format("springblend bake-rig: {} {}/{}", stage == "paths" ? "target paths" : stage, done, total)
              << std::endl;
  };
  return options;
}

nlohmann::json SummaryJson(const BakedRig& baked, const std::string& dir) {
  nlohmann::json targets = nlohmann::json::array();
  for (const BakedTarget& t : baked.targets) {
    std::vector<double> weights;
    for (const BakedShape& s : t.inbetweens) weights.push_back(s.weight);
    targets.push_back({{"name", t.name}, {"inbetweens", weights}, {"snaps", t.snaps}, {"max_error", t.max_error},
                       {"linear_error", t.linear_error}, {"floor", t.floor}});
  }
  nlohmann::json combinations = nlohmann::json::array();
  for (const BakedCombination& c : baked.combinations) {
    std::vector<std::string> drivers;
    for (int d : c.drivers) drivers.push_back(baked.targets[d].name);
    combinations.push_back(
        {{"name", c.name}, {"drivers", drivers}, {"error_without", c.error_without}, {"from_rig", c.from_rig}});
  }
  const BakeSummary& s = baked.summary;
  return {{"rig", (std::filesystem::path(dir) / "rig.json").string()},
          {"targets", targets},
          {"combinations", combinations},
          {"frames", s.frames},
          {"unconverged_frames", s.unconverged_frames},
          {"candidate_pairs", s.candidate_pairs},
          {"kept_pairs", s.kept_pairs},
          {"refused_pairs", s.refused_pairs},
          {"snaps", s.snaps},
          {"max_error", s.max_error},
          {"linear_max_error", s.linear_max_error},
          {"floor", s.floor},
          {"pair_floor", s.pair_floor},
          {"inbetweens", s.solved_inbetweens ? "solved" : "fitted"},
          {"inbetweens_ms", s.inbetweens_ms},
          {"ms", s.ms}};
}

// Frames solved by the server's character, streamed in one Solve call per batch.
FrameSource RemoteFrames(std::shared_ptr<Client> client, std::string id) {
  return [client = std::move(client), id = std::move(id)](const std::vector<std::vector<double>>& weights,
                                                          std::vector<SolvedShape>* out) {
    out->assign(weights.size(), SolvedShape{});
    v1::SolveRequest request;
    request.set_character_id(id);
    for (const auto& w : weights) {
      v1::FrameRequest* frame = request.add_frames();
      for (double x : w) frame->add_weights(x);
    }
    int received = 0;
    try {
      client->Solve(request, [&](const v1::SolvedFrame& frame) {
        if (frame.index() >= weights.size()) {
          throw ClientError(grpc::StatusCode::INTERNAL, "the server answered a frame index out of range");
        }
        SolvedShape& shape = (*out)[frame.index()];
        shape.positions = Client::Decode(frame.positions());
        shape.converged = frame.summary().converged();
        ++received;
      });
    } catch (const ClientError& e) {
      throw CallError("solve", e, fmt::format("{} of {} frames arrived", received, weights.size()));
    }
    if (received != static_cast<int>(weights.size())) {
      throw CallError("solve", ClientError(grpc::StatusCode::INTERNAL, "the stream ended early"),
                      fmt::format("{} of {} frames arrived", received, weights.size()));
    }
  };
}

int RunBake(const BakeArgs& args) {
  const BakeOptions options = OptionsOf(args);
  options.Validate();
  BakeInput input;
  Faces faces;
  FrameSource frames;
  if (!args.character.empty()) {
    if (!args.rest.empty() || !args.targets.empty()) {
      throw Error(ErrorCode::kInvalidInput,
                  "--character bakes a server's character, whose meshes are on the server: drop --rest and --target "
                  "(--rig only says which of its targets are combinations of which)");
    }
    // The character lives on a server: its target names, faces and rest shape (the frame with every weight 0)
    // come from there; a rig file, when given, says which of its targets are combinations of which.
    auto client = std::make_shared<Client>(OpenChannel(args.connection), CallOptions("bake-rig", args.connection));
    const std::string id = ResolveCharacter(*client, "bake-rig", args.character);
    const v1::Character character = Call("get", [&] { return client->Get(id, true); });
    faces.resize(character.faces().size() / 12, 3);
    std::memcpy(faces.data(), character.faces().data(), character.faces().size());
    input.target_names.assign(character.target_names().begin(), character.target_names().end());
    frames = RemoteFrames(client, id);
    std::vector<SolvedShape> rest;
    frames({std::vector<double>(input.target_names.size(), 0.0)}, &rest);
    input.rest = rest[0].positions;
    input.diagonal = (input.rest.colwise().maxCoeff() - input.rest.colwise().minCoeff()).norm();
    if (!args.rig.empty()) {
      const RigFile file = LoadRigFile(args.rig);
      for (const RigTarget& t : file.targets) {
        if (t.combination.empty()) continue;
        BakeInput::Combination c{t.mesh.name, {}};
        for (const std::string& d : t.combination) {
          const auto it = std::find(input.target_names.begin(), input.target_names.end(), d);
          if (it == input.target_names.end()) {
            throw Error(ErrorCode::kInvalidInput,
                        fmt::format("{}: combination '{}' names '{}', not a target of character {}", args.rig,
                                    t.mesh.name, d, id.substr(0, 12)));
          }
          c.drivers.push_back(static_cast<int>(it - input.target_names.begin()));
        }
        input.combinations.push_back(std::move(c));
      }
    } else if (character.combination_names_size() > 0) {
      std::cerr << "springblend bake-rig: note: the character's combinations are not baked without --rig (the "
                   "server names them but not their drivers)"
                << std::endl;
    }
  } else {
    RigOptions rig_options;
    rig_options.fixed_vertices = args.fixed;
    rig_options.hold_outer_rim = args.hold_outer_rim;
    const std::shared_ptr<const Rig> rig =
        BuildRigFromFlags(args.rig, args.rest, args.targets, rig_options, ", or --server and --character");
    input = BakeInputOf(*rig);
    faces = rig->rest().faces;
    frames = LocalFrameSource(rig);
  }
  const BakedRig baked = BakeRig(input, frames, options);
  WriteBakedRig(baked, faces, args.out);
  std::cout << SummaryJson(baked, args.out).dump() << std::endl;
  return baked.summary.unconverged_frames == 0 ? kExitOk : kExitNotConverged;
}

}  // namespace

Runner AddBakeCommand(CLI::App& app) {
  auto args = std::make_shared<BakeArgs>();
  CLI::App* cmd = app.add_subcommand(
      "bake-rig", "bake the physics into a plain blendshape rig (in-betweens and combination correctives) that any "
                  "linear blendshape evaluator plays; writes OUT/rig.json and its meshes, prints a summary as JSON");
  cmd->add_option("--rig", args->rig, "a rig file (JSON); with --server: only for its combinations' drivers");
  cmd->add_option("--rest", args->rest, "rest shape (instead of --rig)");
  cmd->add_option("--target", args->targets, "a target; repeat (order = weight order)");
  cmd->add_option("--out", args->out, "output directory (OUT/rig.json and its OBJ meshes)")->required();
  cmd->add_option("--inbetweens", args->inbetweens,
                  "in-betweens per target (with --tolerance: at most this many)")
      ->check(CLI::Range(0, 1023));
  cmd->add_option("--tolerance", args->tolerance,
                  "the fewest in-betweens that keep each path within this fraction of the diagonal")
      ->check(CLI::Range(0.0, 1.0));
  cmd->add_option("--samples", args->samples, "weights per unit at which each target's path is solved")
      ->check(CLI::Range(2, 1024));
  cmd->add_flag("--solved-inbetweens", args->solved_inbetweens,
                "in-betweens are the solved frames at their weights (reproduced exactly), not shapes fitted to the "
                "whole path (about half the error)");
  cmd->add_option("--pairs", args->pairs,
                  "auto (pairs that move a common region and interact by more than --pair-threshold), none, or "
                  "A*B,C*D");
  cmd->add_option("--pair-threshold", args->pair_threshold,
                  "auto: a pair whose solved mix is farther than this fraction of the diagonal from the sum of its "
                  "parts gets a corrective");
  cmd->add_option("--fixed", args->fixed, "fixed vertices (local rigs)")->delimiter(',');
  cmd->add_flag("--hold-outer-rim", args->hold_outer_rim, "hold an open surface's outer rim (local rigs)");
  Connection& connection = args->connection;
  cmd->add_option("--character", args->character,
                  "bake a server's character (id, 12 or more of its hex digits, or name): frames solved there");
  AddConnectionFlags(cmd, &connection);
  return [args] { return RunExplained("bake-rig", args->connection, [&] { return RunBake(*args); }); };
}

}  // namespace springblend::cli
