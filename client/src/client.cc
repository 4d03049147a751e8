#include "springblend/client.h"

#include <algorithm>
#include <iterator>
#include <grpcpp/grpcpp.h>

#include <cstring>
#include <fstream>
#include <future>
#include <sstream>

#include <fmt/format.h>

#include "grpc/health/v1/health.grpc.pb.h"

namespace springblend {
namespace {

void Check(const grpc::Status& status) {
  if (!status.ok()) throw ClientError(status.error_code(), status.error_message());
}

std::string ReadPem(const char* field, const std::string& path) {
  if (path.empty()) return "";
  std::ifstream in(path, std::ios::binary);
  std::ostringstream text;
  text << in.rdbuf();
  if (!in || text.str().find("-----BEGIN ") == std::string::npos) {
    throw ClientError(grpc::StatusCode::INVALID_ARGUMENT, fmt::format("{}: cannot read a PEM file at {}", field, path));
  }
  return text.str();
}

std::shared_ptr<grpc::ChannelCredentials> Credentials(const ClientOptions& options) {
  if (!options.UsesTls()) return grpc::InsecureChannelCredentials();
  if (options.tls_cert_file.empty() != options.tls_key_file.empty()) {
    throw ClientError(grpc::StatusCode::INVALID_ARGUMENT, "tls_cert_file and tls_key_file go together");
  }
  grpc::SslCredentialsOptions ssl;
  ssl.pem_root_certs = ReadPem("tls_root_ca_file", options.tls_root_ca_file);
  ssl.pem_cert_chain = ReadPem("tls_cert_file", options.tls_cert_file);
  ssl.pem_private_key = ReadPem("tls_key_file", options.tls_key_file);
  return grpc::SslCredentials(ssl);
}

}  // namespace

Client::Client(ClientOptions options) : options_(std::move(options)) {
  grpc::ChannelArguments arguments;
  arguments.SetMaxReceiveMessageSize(256 << 20);
  if (!options_.tls_server_name.empty()) arguments.SetSslTargetNameOverride(options_.tls_server_name);
  channel_ = grpc::CreateCustomChannel(options_.address, Credentials(options_), arguments);
  characters_ = v1::CharacterService::NewStub(channel_);
  solves_ = v1::SolveService::NewStub(channel_);
}

Client::Client(std::shared_ptr<grpc::Channel> channel, ClientOptions options)
    : options_(std::move(options)), channel_(std::move(channel)) {
  characters_ = v1::CharacterService::NewStub(channel_);
  solves_ = v1::SolveService::NewStub(channel_);
}

std::optional<std::string> WeightsByName(const std::vector<std::pair<std::string, double>>& named,
                                         const std::vector<std::string>& names, std::vector<double>* weights) {
  weights->assign(names.size(), 0.0);
  std::vector<char> seen(names.size(), 0);
  for (const auto& [name, value] : named) {
    const auto it = std::find(names.begin(), names.end(), name);
    if (it == names.end()) {
      std::string known;
      for (const auto& n : names) known += (known.empty() ? "" : ", ") + n;
      return fmt::format("'{}' is not a target of this character (targets: {})", name, known.empty() ? "none" : known);
    }
    const auto t = static_cast<size_t>(it - names.begin());
    if (seen[t]) return fmt::format("'{}' is given twice", name);
    seen[t] = 1;
    (*weights)[t] = value;
  }
  return std::nullopt;
}

const char* StatusName(int code) {
  static constexpr const char* kNames[] = {
      "OK",        "CANCELLED",      "UNKNOWN",           "INVALID_ARGUMENT",   "DEADLINE_EXCEEDED",
      "NOT_FOUND", "ALREADY_EXISTS", "PERMISSION_DENIED", "RESOURCE_EXHAUSTED", "FAILED_PRECONDITION",
      "ABORTED",   "OUT_OF_RANGE",   "UNIMPLEMENTED",     "INTERNAL",           "UNAVAILABLE",
      "DATA_LOSS", "UNAUTHENTICATED"};
  return code >= 0 && code < static_cast<int>(std::size(kNames)) ? kNames[code] : "UNKNOWN";
}

v1::Collider MeshCollider(const Points& vertices, const Faces& triangles) {
  if (vertices.rows() == 0 || triangles.rows() == 0) {
    throw ClientError(grpc::StatusCode::INVALID_ARGUMENT, "a mesh collider needs vertices and triangles");
  }
  v1::Collider collider;
  v1::MeshArrays* mesh = collider.mutable_mesh();
  // Row-major Eigen storage is the wire's packed triples (little-endian on our targets).
  mesh->set_positions(reinterpret_cast<const char*>(vertices.data()), sizeof(double) * static_cast<size_t>(vertices.size()));
  mesh->set_triangles(reinterpret_cast<const char*>(triangles.data()), sizeof(int) * static_cast<size_t>(triangles.size()));
  return collider;
}

std::unique_ptr<grpc::ClientContext> Client::Context(const std::string& character) const {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + options_.timeout);
  if (!character.empty()) context->AddMetadata(kCharacterHeader, character);
  if (!options_.token.empty()) context->AddMetadata("authorization", "Bearer " + options_.token);
  return context;
}

v1::Character Client::Upload(const TriangleMesh& rest, const std::vector<TriangleMesh>& targets,
                             const v1::BuildOptions& options, const std::string& name,
                             const UploadProgress& progress) {
  std::vector<RigTarget> plain(targets.size());
  for (size_t t = 0; t < targets.size(); ++t) plain[t].mesh = targets[t];
  return UploadRig(rest, plain, options, name, progress);
}

namespace {

// Only the rest mesh's faces travel; every shape must share them and the vertex count, so check that here.
void CheckTopology(const TriangleMesh& rest, const TriangleMesh& shape) {
  if (shape.vertices.rows() != rest.vertices.rows()) {
    throw ClientError(grpc::StatusCode::INVALID_ARGUMENT,
                      fmt::format("{}: {} vertices, but the rest mesh has {}", shape.source, shape.vertices.rows(),
                                  rest.vertices.rows()));
  }
  if (shape.faces.rows() != rest.faces.rows()) {
    throw ClientError(grpc::StatusCode::INVALID_ARGUMENT,
                      fmt::format("{}: {} faces, but the rest mesh has {}", shape.source, shape.faces.rows(), rest.faces.rows()));
  }
  for (Eigen::Index f = 0; f < rest.faces.rows(); ++f) {
    if (shape.faces.row(f) != rest.faces.row(f)) {
      throw ClientError(grpc::StatusCode::INVALID_ARGUMENT,
                        fmt::format("{}: face {} differs from the rest mesh's; every target must have the rest "
                                    "mesh's faces",
                                    shape.source, f));
    }
  }
}

}  // namespace

v1::Character Client::UploadRig(const TriangleMesh& rest, const std::vector<RigTarget>& targets,
                                const v1::BuildOptions& options, const std::string& name,
                                const UploadProgress& progress) {
  std::vector<const TriangleMesh*> shapes = {&rest};  // the POSITIONS arrays, in the proto's shape order
  bool production = false;
  for (const auto& t : targets) {
    CheckTopology(rest, t.mesh);
    shapes.push_back(&t.mesh);
    production = production || !t.inbetweens.empty() || !t.mask.empty() || !t.combination.empty();
    if (!t.mask.empty() && t.mask.size() != static_cast<size_t>(rest.vertices.rows())) {
      throw ClientError(grpc::StatusCode::INVALID_ARGUMENT,
                        fmt::format("target '{}': mask has {} values, but the rest mesh has {} vertices", t.mesh.name,
                                    t.mask.size(), rest.vertices.rows()));
    }
  }
  for (const auto& t : targets) {
    for (const auto& b : t.inbetweens) {
      CheckTopology(rest, b.mesh);
      shapes.push_back(&b.mesh);
    }
  }
  // Routed as its solves will be: by the id the server will give it.
  auto context = Context(CharacterId(rest, targets, options));
  v1::Character response;
  auto writer = characters_->UploadCharacter(context.get(), &response);
  v1::UploadChunk header;
  v1::UploadHeader* h = header.mutable_header();
  h->set_name(name);
  h->set_vertex_count(static_cast<std::uint32_t>(rest.vertices.rows()));
  h->set_face_count(static_cast<std::uint32_t>(rest.faces.rows()));
  for (const auto& t : targets) {
    h->add_target_names(t.mesh.name);
    if (!production) continue;
    v1::TargetRig* rig = h->add_targets();
    for (const auto& b : t.inbetweens) rig->add_inbetween_weights(b.weight);
    rig->set_has_mask(!t.mask.empty());
    for (const auto& driver : t.combination) rig->add_combination(driver);
  }
  *h->mutable_options() = options;
  bool ok = writer->Write(header);
  auto send = [&](v1::MeshPiece::Kind kind, std::uint32_t shape, const char* data, size_t elements, size_t size) {
    const size_t per_piece = std::max<size_t>(1, options_.piece_bytes / size);
    for (size_t first = 0; ok && first < elements; first += per_piece) {
      const size_t count = std::min(per_piece, elements - first);
      v1::UploadChunk chunk;
      v1::MeshPiece* piece = chunk.mutable_piece();
      piece->set_kind(kind);
      piece->set_shape(shape);
      piece->set_offset(static_cast<std::uint32_t>(first));
      piece->set_data(data + first * size, count * size);
      ok = writer->Write(chunk);
    }
  };
  send(v1::MeshPiece::FACES, 0, reinterpret_cast<const char*>(rest.faces.data()),
       static_cast<size_t>(rest.faces.rows()), 12);
  for (size_t s = 0; s < shapes.size(); ++s) {
    send(v1::MeshPiece::POSITIONS, static_cast<std::uint32_t>(s),
         reinterpret_cast<const char*>(shapes[s]->vertices.data()), static_cast<size_t>(rest.vertices.rows()), 24);
  }
  for (size_t t = 0; t < targets.size(); ++t) {
    if (targets[t].mask.empty()) continue;
    send(v1::MeshPiece::MASK, static_cast<std::uint32_t>(t), reinterpret_cast<const char*>(targets[t].mask.data()),
         targets[t].mask.size(), 8);
  }
  writer->WritesDone();
  if (!progress) {
    Check(writer->Finish());
    return response;
  }
  // The server names the character in its initial metadata once the pieces are checked; the build's progress
  // is then polled with GetCharacter(no_wait) while another thread waits for the upload's answer.
  writer->WaitForInitialMetadata();
  std::string id;
  const auto& metadata = context->GetServerInitialMetadata();
  if (const auto it = metadata.find(kCharacterIdMetadata); it != metadata.end()) id.assign(it->second.data(), it->second.size());
  auto finished = std::async(std::launch::async, [&writer] { return writer->Finish(); });
  while (!id.empty() && finished.wait_for(std::chrono::milliseconds(500)) != std::future_status::ready) {
    try {
      const v1::Character state = Get(id, false, true);
      if (state.state() == v1::CHARACTER_STATE_BUILDING) progress(id, state.build());
    } catch (const ClientError&) {
      // Progress is best effort: the upload's own answer says how it went.
    }
  }
  Check(finished.get());
  return response;
}

v1::Character Client::Get(const std::string& id, bool with_faces, bool no_wait) {
  auto context = Context(id);
  v1::GetCharacterRequest request;
  request.set_id(id);
  request.set_with_faces(with_faces);
  request.set_no_wait(no_wait);
  v1::Character response;
  Check(characters_->GetCharacter(context.get(), request, &response));
  return response;
}

std::vector<v1::Character> Client::List() {
  auto context = Context();
  v1::ListCharactersResponse response;
  Check(characters_->ListCharacters(context.get(), {}, &response));
  return {response.characters().begin(), response.characters().end()};
}

void Client::Delete(const std::string& id) {
  auto context = Context(id);
  v1::DeleteCharacterRequest request;
  request.set_id(id);
  v1::DeleteCharacterResponse response;
  Check(characters_->DeleteCharacter(context.get(), request, &response));
}

bool Client::Healthy() {
  auto stub = grpc::health::v1::Health::NewStub(channel_);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(5));
  grpc::health::v1::HealthCheckRequest request;
  grpc::health::v1::HealthCheckResponse response;
  const grpc::Status status = stub->Check(&context, request, &response);
  return status.ok() && response.status() == grpc::health::v1::HealthCheckResponse::SERVING;
}

int Client::Solve(const v1::SolveRequest& request, const std::function<void(const v1::SolvedFrame&)>& on_frame) {
  auto context = Context(request.character_id());
  auto reader = solves_->Solve(context.get(), request);
  v1::SolvedFrame frame;
  int received = 0;
  while (reader->Read(&frame)) {
    on_frame(frame);
    ++received;
  }
  Check(reader->Finish());
  return received;
}

std::unique_ptr<InteractiveSession> Client::StartInteractive(const v1::InteractiveStart& start) {
  auto session = std::unique_ptr<InteractiveSession>(new InteractiveSession());
  session->context_ = Context(start.character_id());
  session->stream_ = solves_->Interactive(session->context_.get());
  v1::InteractiveRequest first;
  *first.mutable_start() = start;
  session->stream_->Write(first);
  return session;
}

bool InteractiveSession::Send(const v1::FrameRequest& frame) {
  v1::InteractiveRequest request;
  *request.mutable_frame() = frame;
  return stream_->Write(request);
}

bool InteractiveSession::Next(v1::SolvedFrame* frame) { return stream_->Read(frame); }

void InteractiveSession::Close() { stream_->WritesDone(); }

void InteractiveSession::Finish() { Check(stream_->Finish()); }

Points Client::Decode(const std::string& packed) {
  const size_t count = packed.size() / (3 * sizeof(float));
  Eigen::Matrix<float, Eigen::Dynamic, 3, Eigen::RowMajor> values(static_cast<Eigen::Index>(count), 3);
  std::memcpy(values.data(), packed.data(), count * 3 * sizeof(float));
  return values.cast<double>();
}

}  // namespace springblend
