// The remote commands: upload, solve, list, delete and health against a springblend server.
#include <fmt/format.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <optional>
#include <nlohmann/json.hpp>
#include <sstream>

#include "collider_syntax.h"
#include "commands.h"
#include "frame_output.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "remote_call.h"
#include "rig_file.h"
#include "scene.h"
#include "springblend/client.h"
#include "springblend/error.h"

namespace springblend::cli {
namespace {

struct RemoteArgs {
  Connection connection;
  // upload
  std::string rig, rest, name;
  std::vector<std::string> targets;
  std::vector<int> fixed;
  bool no_interior = false, no_anchor = false, no_target_paths = false, hold_outer_rim = false;
  double static_tolerance = 0.0, bending_stiffness = 0.0;  // 0: the server's defaults
  std::uint32_t path_intervals = 0, path_max_samples = 0;   // 0: the server's defaults
  // solve
  std::string character, out;
  FramesInput input;  // --frames, --take, --map, --lost
  std::vector<std::string> weights;  // numbers, or NAME=NUMBER
  CacheTiming timing;
  int sweep = 0;
  std::vector<std::string> colliders, pins;
  double tolerance = 0.0;
  int max_iterations = 0;
  bool linear = false, normals = false, certify = false;
  std::string mix;  // empty: the server's default
  std::optional<std::vector<std::string>> linear_targets;  // nullopt: the server's default
};

v1::Vec3 ToVec3(double x, double y, double z) {
  v1::Vec3 v;
  v.set_x(x), v.set_y(y), v.set_z(z);
  return v;
}

v1::Collider ToProto(const std::string& spec) {
  const ColliderSpec c = ParseColliderSpec(spec);
  const std::vector<double>& v = c.values;
  v1::Collider out;
  if (c.kind == "sphere") {
    *out.mutable_sphere()->mutable_center() = ToVec3(v[0], v[1], v[2]);
    out.mutable_sphere()->set_radius(v[3]);
  } else if (c.kind == "capsule") {
    *out.mutable_capsule()->mutable_a() = ToVec3(v[0], v[1], v[2]);
    *out.mutable_capsule()->mutable_b() = ToVec3(v[3], v[4], v[5]);
    out.mutable_capsule()->set_radius(v[6]);
  } else if (c.kind == "box") {
    *out.mutable_box()->mutable_center() = ToVec3(v[0], v[1], v[2]);
    *out.mutable_box()->mutable_half_extents() = ToVec3(v[3], v[4], v[5]);
  } else if (c.kind == "plane") {
    *out.mutable_plane()->mutable_point() = ToVec3(v[0], v[1], v[2]);
    *out.mutable_plane()->mutable_normal() = ToVec3(v[3], v[4], v[5]);
  } else {
    // Any format the loader reads travels as arrays.
    const TriangleMesh mesh = LoadMesh(c.path);
    out = MeshCollider(mesh.vertices, mesh.faces);
  }
  return out;
}

v1::FrameRequest ToProto(const Frame& frame) {
  v1::FrameRequest out;
  for (double w : frame.weights) out.add_weights(w);
  for (const auto& m : frame.collider_transforms) {
    v1::Transform* t = out.add_collider_transforms();
    *t->mutable_translation() = ToVec3(m.translation.x(), m.translation.y(), m.translation.z());
    t->set_qw(m.rotation.w()), t->set_qx(m.rotation.x()), t->set_qy(m.rotation.y()), t->set_qz(m.rotation.z());
  }
  for (const auto& p : frame.pins) {
    v1::Pin* pin = out.add_pins();
    pin->set_vertex(static_cast<std::uint32_t>(p.vertex));
    *pin->mutable_position() = ToVec3(p.position.x(), p.position.y(), p.position.z());
  }
  return out;
}

nlohmann::json CharacterJson(const v1::Character& c) {
  const v1::RigSummary& s = c.summary();
  return {{"id", c.id()},
          {"name", c.name()},
          {"cache_hit", c.cache_hit()},
          {"targets", std::vector<std::string>(c.target_names().begin(), c.target_names().end())},
          {"combinations", std::vector<std::string>(c.combination_names().begin(), c.combination_names().end())},
          {"vertices", s.vertices()},
          {"surface_vertices", s.surface_vertices()},
          {"springs", s.springs()},
          {"tetrahedra", s.tetrahedra()},
          {"interior", s.interior()},
          {"boundary_mode", s.boundary_mode()},
          {"precompute_ms", s.precompute_ms()},
          {"paths_loaded", s.paths_loaded()},
          {"path_samples", s.path_samples()},
          {"path_ms", s.path_ms()},
          {"static_vertices", s.static_vertices()},
          {"rim_vertices", s.rim_vertices()},
          {"notes", std::vector<std::string>(s.notes().begin(), s.notes().end())}};
}

// The command's client: the channel its flags describe, its token and its deadline per call.
Client ClientFor(const std::string& command, const RemoteArgs& args) {
  return Client(OpenChannel(args.connection), CallOptions(command, args.connection));
}

// READY, BUILDING, STORED (the proto's names without their prefix).
std::string StateName(v1::CharacterState state) {
  const std::string name = v1::CharacterState_Name(state);
  constexpr std::string_view kPrefix = "CHARACTER_STATE_";
  return name.rfind(kPrefix, 0) == 0 ? name.substr(kPrefix.size()) : name;
}

// The build's progress on stderr while an upload waits: a line when the stage or the targets done change, and
// at least every 10 s (the JSON answer alone goes to stdout).
Client::UploadProgress ProgressPrinter() {
  struct Last {
    std::string stage;
    std::uint32_t targets_done = 0;
    double printed_ms = -1e300;
  };
  auto last = std::make_shared<Last>();
  return [last](const std::string& id, const v1::BuildProgress& p) {
    if (p.stage() == last->stage && p.targets_done() == last->targets_done && p.elapsed_ms() - last->printed_ms < 10000) {
      return;
    }
    last->stage = p.stage();
    last->targets_done = p.targets_done();
    last->printed_ms = p.elapsed_ms();
    std::string line = fmt::format("building {}: {}", id.substr(0, 12), p.stage());
    if (p.targets() > 0) line += fmt::format(", target paths {}/{} ({} samples)", p.targets_done(), p.targets(), p.path_samples());
    line += fmt::format(", {:.0f} s", p.elapsed_ms() / 1000.0);
    if (p.estimate_ms() > 0) line += fmt::format(" of about {:.0f} s", p.estimate_ms() / 1000.0);
    if (p.from_cache_file()) line += " (rebuilt from the server's cache directory)";
    std::cerr << line << std::endl;
  };
}

int RunUpload(const RemoteArgs& args) {
  Client client = ClientFor("upload", args);
  const Client::UploadProgress progress = ProgressPrinter();
  v1::BuildOptions options;
  for (int v : args.fixed) options.add_fixed_vertices(static_cast<std::uint32_t>(v));
  options.set_no_interior(args.no_interior);
  options.set_no_anchor(args.no_anchor);
  options.set_no_target_paths(args.no_target_paths);
  options.set_hold_outer_rim(args.hold_outer_rim);
  options.set_static_tolerance(args.static_tolerance);
  options.set_bending_stiffness(args.bending_stiffness);
  options.set_path_intervals(args.path_intervals);
  options.set_path_max_samples(args.path_max_samples);
  v1::Character c;
  if (!args.rig.empty()) {
    if (!args.rest.empty() || !args.targets.empty()) {
      throw Error(ErrorCode::kInvalidInput, "--rig names the rest shape and the targets; drop --rest and --target");
    }
    const RigFile rig = LoadRigFile(args.rig);
    for (int v : rig.fixed_vertices) options.add_fixed_vertices(static_cast<std::uint32_t>(v));
    c = Call("upload", [&] {
      try {
        return client.UploadRig(rig.rest, rig.targets, options, args.name.empty() ? rig.rest.name : args.name,
                                progress);
      } catch (const ClientError& e) {
        // The server's refusal names the target and the field; say which file they are in.
        throw ClientError(e.code(), fmt::format("{}: {}", rig.path, e.what()));
      }
    });
  } else {
    if (args.rest.empty() || args.targets.empty()) {
      throw Error(ErrorCode::kInvalidInput, "give --rest and at least one --target, or --rig RIG.json");
    }
    TriangleMesh rest = LoadMesh(args.rest);
    std::vector<TriangleMesh> targets;
    for (const auto& t : args.targets) targets.push_back(LoadMesh(t));
    c = Call("upload", [&] {
      return client.Upload(rest, targets, options, args.name.empty() ? rest.name : args.name, progress);
    });
  }
  // The rig builder's notes (a floating rig, the held rim, ...) are for the person uploading: say them.
  for (const std::string& note : c.summary().notes()) std::cerr << "springblend upload: note: " << note << std::endl;
  std::cout << CharacterJson(c).dump() << std::endl;
  return kExitOk;
}

int RunSolve(const RemoteArgs& args) {
  Client client = ClientFor("solve", args);
  const std::string id = ResolveCharacter(client, "solve", args.character);
  const v1::Character character =
      Call("get (the character's faces, before the solve)", [&] { return client.Get(id, true); });
  Faces faces(character.faces().size() / 12, 3);
  std::memcpy(faces.data(), character.faces().data(), character.faces().size());

  v1::SolveRequest request;
  request.set_character_id(id);
  std::vector<Frame> frames;
  std::vector<std::string> collider_specs;
  CacheTiming timing = args.timing;
  if (args.input.given()) {
    Scene scene = LoadFrames(args.input, {character.target_names().begin(), character.target_names().end()}, &timing);
    frames = std::move(scene.frames);
    collider_specs = scene.colliders;
  } else {
    args.input.CheckTakeOptionsUnused();
    std::vector<double> weights = ResolveWeights(
        ParseWeightItems(args.weights), {character.target_names().begin(), character.target_names().end()},
        "--weights");
    if (weights.empty() && character.target_names_size() == 1) weights = {1.0};
    if (weights.empty()) {
      throw Error(ErrorCode::kInvalidInput, fmt::format("--weights is required: the character has {} targets",
                                                        character.target_names_size()));
    }
    if (args.sweep > 0) {
      frames = SweepFrames(weights, args.sweep);
    } else {
      frames.push_back(Frame{weights});
    }
  }
  collider_specs.insert(collider_specs.end(), args.colliders.begin(), args.colliders.end());
  for (const auto& spec : collider_specs) *request.add_colliders() = ToProto(spec);
  for (const auto& spec : args.pins) {
    const Pin pin = ParsePin(spec);
    for (Frame& f : frames) f.pins.push_back(pin);
  }
  for (const Frame& f : frames) *request.add_frames() = ToProto(f);
  request.mutable_options()->set_residual_tolerance(args.tolerance);
  request.mutable_options()->set_max_iterations(static_cast<std::uint32_t>(args.max_iterations));
  request.mutable_options()->set_linear(args.linear);
  request.mutable_options()->set_with_normals(args.normals);
  request.mutable_options()->set_certify_minimum(args.certify);
  request.mutable_options()->set_mix(args.mix);
  if (args.linear_targets) {
    auto* names = request.mutable_options()->mutable_linear_targets()->mutable_names();
    if (!(args.linear_targets->size() == 1 && args.linear_targets->front() == "none")) {
      for (const auto& name : *args.linear_targets) *names->Add() = name;
    }
  }

  FrameOutput output(args.out, /*many=*/true, faces, static_cast<int>(character.summary().surface_vertices()),
                     timing);
  const bool progress = isatty(STDERR_FILENO) && isatty(STDOUT_FILENO);
  const auto start = std::chrono::steady_clock::now();
  bool all_converged = true;
  const int total = request.frames_size();
  int received = 0;
  auto on_frame = [&](const v1::SolvedFrame& frame) {
    ++received;
    // When the frame arrived, from the start of the call (before the OBJ below is written).
    const double received_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    output.Write(static_cast<int>(frame.index()), Client::Decode(frame.positions()));
    const v1::FrameSummary& s = frame.summary();
    all_converged = all_converged && s.converged();
    const nlohmann::json line = {{"frame", frame.index()}, {"converged", s.converged()},
                                 {"termination", s.termination()}, {"message", s.message()},
                                 {"newton_iterations", s.newton_iterations()}, {"residual", s.residual()},
                                 {"contacts", s.contacts()}, {"pins", s.pins()},
                                 {"inverted_tetrahedra", s.inverted_tetrahedra()}, {"finish", s.finish()},
                                 {"solved_vertices", s.solved_vertices()}, {"minimum", s.minimum()},
                                 {"solve_ms", s.solve_ms()},
                                 {"received_ms", received_ms}, {"served_by", s.served_by()}};
    if (progress) {
      const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
      const int done = static_cast<int>(frame.index()) + 1;
      const int width = 30, filled = width * done / std::max(total, 1);
      std::cerr << fmt::format("\r[{}{}] {}/{} frames, {:.1f} frames/s ", std::string(filled, '#'),
                               std::string(width - filled, '.'), done, total, done / std::max(seconds, 1e-9))
                << std::flush;
    } else {
      std::cout << line.dump() << std::endl;
    }
  };
  try {
    client.Solve(request, on_frame);
  } catch (const ClientError& e) {
    if (progress) std::cerr << "\n";
    throw CallError("solve", e, fmt::format("{} of {} frames arrived", received, total));
  }
  if (progress) std::cerr << "\n";
  output.Finish();
  return all_converged ? kExitOk : kExitNotConverged;
}

int RunList(const RemoteArgs& args) {
  Client client = ClientFor("list", args);
  for (const auto& c : Call("list", [&] { return client.List(); })) std::cout << CharacterJson(c).dump() << std::endl;
  return kExitOk;
}

int RunDelete(const RemoteArgs& args) {
  Client client = ClientFor("delete", args);
  const std::string id = ResolveCharacter(client, "delete", args.character);
  Call("delete", [&] { client.Delete(id); });
  std::cout << nlohmann::json({{"deleted", id}}).dump() << std::endl;
  return kExitOk;
}

// One character as a JSON line: what `list` shows and the rest of its summary, its state (READY, BUILDING with
// the build's progress, STORED: only in the server's cache directory) and its build's times. Answers at once,
// also while the character is being built.
int RunDescribe(const RemoteArgs& args) {
  Client client = ClientFor("describe", args);
  const std::string id = ResolveCharacter(client, "describe", args.character);
  const v1::Character c = Call("describe", [&] { return client.Get(id, false, /*no_wait=*/true); });
  const v1::RigSummary& s = c.summary();
  nlohmann::json out = CharacterJson(c);
  out.erase("cache_hit");
  out["state"] = StateName(c.state());
  out["faces"] = s.faces();
  out["interior_reason"] = s.interior_reason();
  out["interior_vertices"] = s.interior_vertices();
  out["anchor_vertices"] = s.anchor_vertices();
  out["uncertified_path_intervals"] = s.uncertified_path_intervals();
  out["path_max_error"] = s.path_max_error();
  out["path_bytes"] = s.path_bytes();
  out["path_file_bytes"] = s.path_file_bytes();
  out["rig_bytes"] = s.rig_bytes();
  nlohmann::json paths = nlohmann::json::array();
  for (const v1::TargetPathSummary& p : s.paths()) {
    nlohmann::json ranges = nlohmann::json::array();
    for (const v1::WeightRange& r : p.uncertified_ranges()) ranges.push_back({r.low(), r.high()});
    paths.push_back({{"target", p.target()},
                     {"samples", p.samples()},
                     {"solves", p.solves()},
                     {"checks", p.checks()},
                     {"local_checks", p.local_checks()},
                     {"ms", p.ms()},
                     {"max_error", p.max_error()},
                     {"uncertified", p.uncertified()},
                     {"uncertified_ranges", ranges}});
  }
  out["paths"] = paths;
  if (c.state() == v1::CHARACTER_STATE_BUILDING) {
    const v1::BuildProgress& p = c.build();
    out["build"] = {{"stage", p.stage()},           {"targets", p.targets()},
                    {"targets_done", p.targets_done()}, {"path_samples", p.path_samples()},
                    {"elapsed_ms", p.elapsed_ms()},     {"estimate_ms", p.estimate_ms()},
                    {"from_cache_file", p.from_cache_file()}};
  }
  std::cout << out.dump() << std::endl;
  return kExitOk;
}

// The standard health service, asked directly (Client::Healthy says only true or false): a server that
// answers NOT_SERVING is told apart from one that cannot be reached.
int RunHealth(const RemoteArgs& args) {
  using Health = grpc::health::v1::HealthCheckResponse;
  const std::string address = ResolveAddress(args.connection).address;
  auto stub = grpc::health::v1::Health::NewStub(OpenChannel(args.connection));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + *CommandDeadline("health", args.connection));
  Health response;
  const grpc::Status status = stub->Check(&context, grpc::health::v1::HealthCheckRequest(), &response);
  if (!status.ok()) {
    const bool unreachable = status.error_code() == grpc::StatusCode::UNAVAILABLE ||
                             status.error_code() == grpc::StatusCode::DEADLINE_EXCEEDED;
    std::cout << nlohmann::json({{"server", address},
                                 {"status", unreachable ? "UNREACHABLE" : "ERROR"},
                                 {"code", StatusName(status.error_code())}})
                     .dump()
              << std::endl;
    throw CallError("health", ClientError(status.error_code(), status.error_message()));
  }
  const std::string serving = Health::ServingStatus_Name(response.status());
  std::cout << nlohmann::json({{"server", address}, {"status", serving}}).dump() << std::endl;
  return response.status() == Health::SERVING ? kExitOk : kExitUnavailable;
}

// gRPC failures become a message naming the call, the status and what to do, and an exit code: the caller's
// mistakes 2, the server's state 4.
Runner Guarded(const std::string& command, std::shared_ptr<const RemoteArgs> args,
               std::function<int(const RemoteArgs&)> run) {
  return [command, args = std::move(args), run = std::move(run)] {
    return RunExplained(command, args->connection, [&] { return run(*args); });
  };
}

}  // namespace

std::vector<std::pair<std::string, Runner>> AddServiceCommands(CLI::App& app) {
  auto args = std::make_shared<RemoteArgs>();
  std::vector<std::pair<std::string, Runner>> runners;
  Connection& connection = args->connection;
  const auto server_option = [&](CLI::App* cmd) { AddConnectionFlags(cmd, &connection); };

  CLI::App* upload = app.add_subcommand("upload", "upload a character; prints its id and rig summary as JSON");
  server_option(upload);
  upload->add_option("--rig", args->rig, "a rig file (JSON, see README) instead of --rest and --target");
  upload->add_option("--rest", args->rest, "rest shape");
  upload->add_option("--target", args->targets, "a target; repeat (order = weight order)");
  upload->add_option("--name", args->name, "a label (default: the rest file's name)");
  upload->add_option("--fixed", args->fixed, "fixed vertices")->delimiter(',');
  upload->add_flag("--no-interior", args->no_interior, "surface springs only");
  upload->add_flag("--no-anchor", args->no_anchor, "no internal anchor");
  upload->add_flag("--hold-outer-rim", args->hold_outer_rim,
                   "hold an open surface's outer rim (a face mask's; its holes stay free) on the linear blend: the "
                   "rig is then held whatever its targets move, so colliders and pins work");
  upload->add_option("--static-tolerance", args->static_tolerance,
                     "vertices moving less than this fraction of the diagonal in every target are fixed (default "
                     "1e-6); negative disables");
  upload->add_option("--bending-stiffness", args->bending_stiffness,
                     "stiffness of bending springs relative to structure springs (default 1)")
      ->check(CLI::PositiveNumber);
  upload->add_flag("--no-target-paths", args->no_target_paths,
                   "build no target paths: a faster upload, slower frames (still stateless)");
  upload->add_option("--path-intervals", args->path_intervals,
                     "target paths' continuation steps per unit of weight (default 16; denser paths finish more "
                     "frames locally where a character's paths snap often, at more memory and upload time)")
      ->check(CLI::Range(4, 128));
  upload->add_option("--path-max-samples", args->path_max_samples, "samples kept per target path (default 64)")
      ->check(CLI::Range(8, 256));
  runners.emplace_back("upload", Guarded("upload", args, RunUpload));

  CLI::App* solve = app.add_subcommand(
      "solve", "solve frames on the server; writes OUT/frame_0000.obj ... (or OUT.pc2) and JSON lines");
  server_option(solve);
  solve->add_option("--character", args->character,
                    "the character: its id from upload, 12 or more of its first hex digits, or its name")
      ->required();
  solve->add_option("--weights", args->weights,
                    "one weight per target, or by name: jawOpen=0.7,mouthSmile_L=0.3 (the others 0); the sweep's end "
                    "with --sweep")
      ->delimiter(',');
  solve->add_option("--sweep", args->sweep, "N frames from the rest shape to the weights")->check(CLI::Range(1, 100000));
  AddFramesOptions(solve, &args->input);
  solve->add_option("--collider", args->colliders, "an obstacle (as for blend); repeatable");
  solve->add_option("--pin", args->pins, "VERTEX:x,y,z in every frame; repeatable");
  solve->add_option("--out", args->out,
                    "output directory (OUT/frame_0000.obj ...), or a path ending in .pc2: one PC2 point cache of "
                    "every frame (see --start-frame)")
      ->required();
  AddCacheTimingOptions(solve, &args->timing);
  solve->add_option("--tolerance", args->tolerance, "residual tolerance (server default 1e-6)");
  solve->add_option("--max-iterations", args->max_iterations, "Newton iterations per frame");
  solve->add_flag("--linear", args->linear, "the linear blendshape");
  solve->add_flag("--normals", args->normals, "ask for normals too");
  solve->add_flag("--certify", args->certify,
                  "have the server check that each converged answer is a local minimum (about one factorization "
                  "more per frame): the frame's JSON line says \"minimum\": \"minimum\" or \"not_a_minimum\"");
  solve->add_option("--mix", args->mix,
                    "how a frame that moves several targets combines them: superposed (the server's default) or "
                    "rest-lengths (the paper's blend of rest lengths)");
  solve->add_option("--linear-targets", args->linear_targets,
                    "with the superposed mix, targets added as linear deltas (correctives), comma-separated, or none "
                    "(the server's default: mouthClose where the character has it)")
      ->delimiter(',');
  runners.emplace_back("solve", Guarded("solve", args, RunSolve));

  CLI::App* list = app.add_subcommand("list", "list the server's characters as JSON lines");
  server_option(list);
  runners.emplace_back("list", Guarded("list", args, RunList));

  CLI::App* remove = app.add_subcommand("delete", "delete a character from the server and its cache directory");
  server_option(remove);
  remove->add_option("--character", args->character, "the character: its id, 12 or more of its hex digits, or its name")
      ->required();
  runners.emplace_back("delete", Guarded("delete", args, RunDelete));

  CLI::App* describe = app.add_subcommand(
      "describe", "show one character as JSON: targets, vertices, interior, boundary mode, state, build times");
  server_option(describe);
  describe->add_option("--character", args->character, "the character: its id, 12 or more of its hex digits, or its name")
      ->required();
  runners.emplace_back("describe", Guarded("describe", args, RunDescribe));

  CLI::App* health = app.add_subcommand("health", "ask the server's health service; exit 0 when SERVING");
  server_option(health);
  runners.emplace_back("health", Guarded("health", args, RunHealth));
  return runners;
}

}  // namespace springblend::cli
