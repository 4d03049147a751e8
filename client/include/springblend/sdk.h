// The springblend SDK: what a DCC plug-in (a Maya deformer, a Houdini SOP, a game-engine tool) links to talk to
// a springblend server. A shared library (libspringblend_sdk.so.0, CMake target springblend::sdk) whose API is
// plain C++ structs and std types only: no gRPC, Protobuf or Eigen type appears here, so a plug-in does not
// depend on the gRPC and Protobuf of our build (nor collides with its host's), and the library exports nothing
// but this namespace.
//
//   springblend::sdk::Client client({.address = "farm:50051"});
//   const auto character = client.Upload(rest, {{jaw}, {smile}}, {.hold_outer_rim = true}, "face");
//   client.Solve(character.id, {{.weights = {0.7, 0.2}}}, {}, {}, [&](const sdk::SolvedFrame& f) { ... });
//
// Every call throws sdk::Error with the server's status name and message (which names the field at fault).
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#define SPRINGBLEND_SDK_API __attribute__((visibility("default")))

namespace springblend::sdk {

// This library's version ("0.1.0"), for a plug-in to check what it loaded.
SPRINGBLEND_SDK_API const char* Version();

class SPRINGBLEND_SDK_API Error : public std::runtime_error {
 public:
  Error(std::string status, const std::string& message);
  ~Error() override;
  // The gRPC status name: INVALID_ARGUMENT (the message names the field), NOT_FOUND, UNAVAILABLE,
  // DEADLINE_EXCEEDED, RESOURCE_EXHAUSTED, UNAUTHENTICATED, ...
  const std::string& status() const { return status_; }

 private:
  std::string status_;
};

// Where the server is and how to reach it.
struct Connection {
  std::string address = "127.0.0.1:50051";
  double timeout_seconds = 600.0;  // per call
  std::string token;               // sent as "authorization: Bearer TOKEN" (use TLS off loopback)
  // TLS when `tls` is set or any file is given: the server's certificate is checked against tls_root_ca_file
  // (PEM; empty: the system's roots) and must name the host of `address`, or tls_server_name. tls_cert_file and
  // tls_key_file are this client's certificate, for servers that require mutual TLS.
  bool tls = false;
  std::string tls_root_ca_file, tls_cert_file, tls_key_file, tls_server_name;
};

// A triangle mesh as flat arrays: x y z per vertex, three 0-based vertex indices per triangle.
struct Mesh {
  std::string name;  // a target's name (the weight's name)
  std::vector<double> positions;
  std::vector<std::int32_t> triangles;
};

// A blendshape target: its mesh (the rest mesh's vertices and triangles), in-betweens, a per-vertex mask, or
// the drivers of a combination corrective (its mesh: the sculpt with every driver at 1).
struct Target {
  Mesh mesh;
  struct Inbetween {
    double weight = 0.0;  // in (0, 1)
    Mesh mesh;
  };
  std::vector<Inbetween> inbetweens;
  std::vector<double> mask;              // empty, or one weight per vertex
  std::vector<std::string> combination;  // the drivers' names
};

// The rig builder's options; zero values mean the server's defaults.
struct BuildOptions {
  std::vector<std::int32_t> fixed_vertices;  // held on the linear blend
  double static_tolerance = 0.0;             // of the diagonal (default 1e-6); negative: no static vertices
  double bending_stiffness = 0.0;            // relative to edges (default 1)
  bool no_interior = false;
  bool no_anchor = false;
  bool no_target_paths = false;
  bool hold_outer_rim = false;  // hold an open surface's outer rim (a face mask's): colliders then work
  // The target paths' density: steps per unit of weight [4, 128] (default 16) and samples kept per target
  // [8, 256] (default 64). Denser paths finish more single-target frames locally where a character's paths
  // snap often, at more memory and a longer upload.
  int path_intervals = 0;
  int path_max_samples = 0;
};

struct Character {
  std::string id, name;
  std::string state;  // READY, BUILDING, STORED
  bool cache_hit = false;
  std::vector<std::string> target_names;       // the weight order of frames
  std::vector<std::string> combination_names;  // weighted by their drivers
  int vertices = 0, surface_vertices = 0, faces = 0;
  std::string boundary_mode;        // fixed_vertices, partially_fixed, floating, anchored
  std::vector<std::string> notes;   // the rig builder's (a floating rig says how to hold it)
  double precompute_ms = 0.0;
};

// Told how a build goes while an upload waits for it, about twice a second.
struct BuildProgress {
  std::string id, stage;
  int targets = 0, targets_done = 0;
  double elapsed_ms = 0.0, estimate_ms = 0.0;
};

// An obstacle, fixed for a request; a frame moves it by a Transform.
struct SPRINGBLEND_SDK_API Collider {
  enum class Shape { kSphere, kCapsule, kBox, kPlane, kMesh };
  Shape shape = Shape::kSphere;
  std::array<double, 3> a{}, b{};  // sphere, box: centre; capsule: the segment's ends; plane: a point, normal
  double radius = 0.0;             // sphere, capsule
  std::array<double, 3> half_extents{};  // box
  Mesh mesh;                             // a closed, outward-oriented mesh
  static Collider Sphere(std::array<double, 3> centre, double radius);
  static Collider Capsule(std::array<double, 3> a, std::array<double, 3> b, double radius);
  static Collider Box(std::array<double, 3> centre, std::array<double, 3> half_extents);
  static Collider Plane(std::array<double, 3> point, std::array<double, 3> normal);  // solid behind the normal
  static Collider FromMesh(Mesh mesh);
};

struct Transform {
  std::array<double, 3> translation{};
  std::array<double, 4> rotation{1.0, 0.0, 0.0, 0.0};  // quaternion w x y z
};

struct Pin {
  std::int32_t vertex = 0;
  std::array<double, 3> position{};
};

struct Frame {
  std::vector<double> weights;  // one per target name, in order
  // Or by name (the targets not named at 0; an unknown name is refused naming the known ones).
  std::vector<std::pair<std::string, double>> named_weights;
  std::vector<Transform> collider_transforms;  // one per collider, or none
  std::vector<Pin> pins;
};

struct SolveOptions {
  double tolerance = 0.0;  // largest free force (default 1e-6)
  int max_iterations = 0;
  bool linear = false;   // the plain linear blendshape
  bool normals = false;  // per-vertex normals too
  // Certify each converged answer as a local minimum (about one factorization more per frame):
  // SolvedFrame::minimum.
  bool certify_minimum = false;
  // How a frame that moves several targets combines them: "superposed" (empty: the server's default) or
  // "rest-lengths" (the paper's blend); SolveOptions.mix in the protocol.
  std::string mix;
  // Targets added as linear deltas (correctives) with the superposed mix; nullopt: the server's default
  // (SolveOptions.linear_targets in the protocol).
  std::optional<std::vector<std::string>> linear_targets;
};

struct SolvedFrame {
  int index = 0;
  std::vector<float> positions;  // x y z per surface vertex
  std::vector<float> normals;    // when asked for
  bool converged = false;
  std::string termination, message;
  int newton_iterations = 0, contacts = 0;
  double residual = 0.0, solve_ms = 0.0;
  std::string finish;   // full | local (finished only where out of balance) | none
  std::string minimum;  // minimum | not_a_minimum | not_checked (SolveOptions::certify_minimum)
};

class SPRINGBLEND_SDK_API Client {
 public:
  explicit Client(Connection connection);
  ~Client();
  Client(Client&&) noexcept;
  Client& operator=(Client&&) noexcept;

  bool Healthy();
  // Uploads the rest mesh and its targets and waits for the rig's build (seconds to minutes); on_progress runs
  // on the calling thread, and an exception it throws cancels the upload.
  Character Upload(const Mesh& rest, const std::vector<Target>& targets, const BuildOptions& options = {},
                   const std::string& name = "", const std::function<void(const BuildProgress&)>& on_progress = {});
  Character Get(const std::string& id);
  std::vector<Character> List();
  void Delete(const std::string& id);
  // Streams the frames' answers to on_frame as they come; returns how many came.
  int Solve(const std::string& character_id, const std::vector<Frame>& frames,
            const std::vector<Collider>& colliders, const SolveOptions& options,
            const std::function<void(const SolvedFrame&)>& on_frame);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace springblend::sdk
