// The C++ client of a springblend server: what a DCC plug-in written in C++ links. Every call throws
// ClientError carrying the server's status code and message (which names the field at fault).
#pragma once

#include <chrono>
#include <functional>
#include <memory>
#include <utility>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "springblend/geometry.h"
#include "springblend/v1/springblend.grpc.pb.h"

namespace springblend {

// Weights given by target name, placed in a character's weight order (`names`: its target names; the targets
// not named get 0) into *weights. Returns what is wrong in words when a name is unknown or given twice
// ("'jawopen' is not a target of this character (targets: jawOpen, mouthSmile_L)"), else nullopt.
std::optional<std::string> WeightsByName(const std::vector<std::pair<std::string, double>>& named,
                                         const std::vector<std::string>& names, std::vector<double>* weights);

// A grpc::StatusCode's name: "INVALID_ARGUMENT", "UNAVAILABLE", ... ("UNKNOWN" for a number out of range).
const char* StatusName(int code);

class ClientError : public std::runtime_error {
 public:
  ClientError(int code, const std::string& message)
      : std::runtime_error(message), code_(code) {}
  int code() const { return code_; }  // a grpc::StatusCode
 private:
  int code_;
};

struct ClientOptions {
  std::string address = "127.0.0.1:50051";
  std::chrono::milliseconds timeout{std::chrono::minutes(10)};  // per call
  size_t piece_bytes = 1 << 20;  // upload piece size, well under gRPC's 4 MiB message limit

  // Transport security: TLS when `tls` is set or any tls_* file is given. The server's certificate is checked
  // against tls_root_ca_file (PEM; empty: the system's roots) and must name the host of `address`, or
  // tls_server_name when set. tls_cert_file and tls_key_file (PEM) are this client's certificate, for servers
  // that require mutual TLS.
  bool tls = false;
  std::string tls_root_ca_file;
  std::string tls_cert_file;
  std::string tls_key_file;
  std::string tls_server_name;
  // Sent on every call as "authorization: Bearer TOKEN" (empty: none). Use TLS off loopback.
  std::string token;

  bool UsesTls() const {
    return tls || !tls_root_ca_file.empty() || !tls_cert_file.empty() || !tls_key_file.empty();
  }
};

// A mesh collider from arrays (#V by 3 positions, #F by 3 0-based triangles; closed, outward-oriented), sent as
// packed arrays: nothing to format or parse. Throws ClientError(INVALID_ARGUMENT) on an empty mesh.
v1::Collider MeshCollider(const Points& vertices, const Faces& triangles);

// One target of a production rig (README: rig files), as plain arrays: a plug-in needs none of the solver's
// libraries to describe one. Weights blend piecewise linearly through the in-betweens; a combination's weight
// is the product of its drivers'; a mask scales the target's change per vertex.
struct RigTarget {
  TriangleMesh mesh;  // mesh.name is the target's name; a combination's: the sculpt with every driver at 1
  struct Inbetween {
    double weight = 0.0;  // in (0, 1), distinct per target
    TriangleMesh mesh;
  };
  std::vector<Inbetween> inbetweens;
  std::vector<double> mask;              // empty, or one weight per rest-mesh vertex
  std::vector<std::string> combination;  // the drivers' names (>= 2 targets that are not combinations)
};

// The id the server gives a character uploaded with these meshes and options (the name is not part of it), the
// hex SHA-256 of its canonical bytes (docs/server.md#routing). Upload and UploadRig send it as the
// kCharacterHeader of the upload, so a balancer that hashes the header builds the character on the replica its
// solves will reach.
std::string CharacterId(const TriangleMesh& rest, const std::vector<RigTarget>& targets,
                        const v1::BuildOptions& options = {});

// The metadata header that names the character of a call, so a load balancer can route by it (uploads too).
inline constexpr char kCharacterHeader[] = "x-springblend-character";
// The initial metadata in which the server names an upload's character as soon as its pieces are checked.
inline constexpr char kCharacterIdMetadata[] = "springblend-character-id";

// A slider session: Send frames as the user moves; Next returns answers as they come (the server answers the
// newest frame and drops overtaken ones). Close half-closes and drains the remaining answers.
class InteractiveSession {
 public:
  bool Send(const v1::FrameRequest& frame);
  bool Next(v1::SolvedFrame* frame);  // false when the stream has ended
  void Close();                       // then Next until false, then Finish
  void Finish();                      // throws ClientError unless the session ended OK

 private:
  friend class Client;
  std::unique_ptr<grpc::ClientContext> context_;
  std::unique_ptr<grpc::ClientReaderWriter<v1::InteractiveRequest, v1::SolvedFrame>> stream_;
};

class Client {
 public:
  // Connects to options.address, with its TLS settings.
  explicit Client(ClientOptions options);
  // Over a channel the caller made (an in-process channel into a server in this process, or one with
  // settings of its own); options.address and the tls_* fields are then unused, timeout and token apply.
  explicit Client(std::shared_ptr<grpc::Channel> channel, ClientOptions options = {});

  // Told how a build goes while an upload waits for it, about twice a second (on the calling thread): the
  // character's id and the server's BuildProgress (stage, targets and path samples done, elapsed, estimate).
  using UploadProgress = std::function<void(const std::string& id, const v1::BuildProgress& progress)>;
  // Uploads the rest mesh and targets (same vertex count and faces) in pieces, and waits for the build.
  v1::Character Upload(const TriangleMesh& rest, const std::vector<TriangleMesh>& targets,
                       const v1::BuildOptions& options = {}, const std::string& name = "",
                       const UploadProgress& progress = {});
  // A production rig: in-betweens, masks and combinations travel with the meshes (TargetRig in the proto).
  // Solves then take one weight per target that is not a combination, in order.
  v1::Character UploadRig(const TriangleMesh& rest, const std::vector<RigTarget>& targets,
                          const v1::BuildOptions& options = {}, const std::string& name = "",
                          const UploadProgress& progress = {});
  // Waits for a character being built (an upload, or a rebuild after a restart); with no_wait answers at once
  // with its state (READY, BUILDING with build progress, STORED: only in the server's cache directory).
  v1::Character Get(const std::string& id, bool with_faces = false, bool no_wait = false);
  std::vector<v1::Character> List();
  void Delete(const std::string& id);
  // True when the server's standard health service reports SERVING.
  bool Healthy();
  // Streams the frames; on_frame runs for each as it arrives. Returns the number of frames received.
  int Solve(const v1::SolveRequest& request, const std::function<void(const v1::SolvedFrame&)>& on_frame);

  std::unique_ptr<InteractiveSession> StartInteractive(const v1::InteractiveStart& start);

  // Decodes a SolvedFrame's float32 positions (or normals) into #V by 3 doubles.
  static Points Decode(const std::string& packed);

 private:
  std::unique_ptr<grpc::ClientContext> Context(const std::string& character = "") const;

  ClientOptions options_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::CharacterService::Stub> characters_;
  std::unique_ptr<v1::SolveService::Stub> solves_;
};

}  // namespace springblend
