// The SDK's plain structs to and from the client library's messages. Everything here but springblend::sdk is
// hidden in the shared library (sdk.map), so the gRPC and Protobuf it links never meet a host's own.
#include "springblend/sdk.h"

#include <fmt/format.h>
#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <map>

#include "springblend/client.h"
#include "springblend/version.h"

namespace springblend::sdk {
namespace {

Error Invalid(const std::string& message) { return Error("INVALID_ARGUMENT", message); }

// Runs a client call, turning the library's errors into sdk::Error.
template <typename Fn>
auto Guard(Fn&& fn) -> decltype(fn()) {
  try {
    return fn();
  } catch (const ClientError& e) {
    throw Error(StatusName(e.code()), e.what());
  }
}

TriangleMesh ToMesh(const Mesh& mesh, const std::string& what) {
  if (mesh.positions.size() % 3 != 0) {
    throw Invalid(fmt::format("{}: positions has {} numbers, not 3 per vertex", what, mesh.positions.size()));
  }
  if (mesh.triangles.size() % 3 != 0) {
    throw Invalid(fmt::format("{}: triangles has {} indices, not 3 per triangle", what, mesh.triangles.size()));
  }
  TriangleMesh out;
  out.name = mesh.name;
  out.source = what;
  const auto vertices = static_cast<Eigen::Index>(mesh.positions.size() / 3);
  const auto faces = static_cast<Eigen::Index>(mesh.triangles.size() / 3);
  out.vertices = Eigen::Map<const Points>(mesh.positions.data(), vertices, 3);
  out.faces = Eigen::Map<const Faces>(mesh.triangles.data(), faces, 3);
  return out;
}

v1::Vec3 ToVec3(const std::array<double, 3>& v) {
  v1::Vec3 out;
  out.set_x(v[0]), out.set_y(v[1]), out.set_z(v[2]);
  return out;
}

v1::Collider ToCollider(const Collider& c, size_t index) {
  v1::Collider out;
  switch (c.shape) {
    case Collider::Shape::kSphere:
      *out.mutable_sphere()->mutable_center() = ToVec3(c.a);
      out.mutable_sphere()->set_radius(c.radius);
      break;
    case Collider::Shape::kCapsule:
      *out.mutable_capsule()->mutable_a() = ToVec3(c.a);
      *out.mutable_capsule()->mutable_b() = ToVec3(c.b);
      out.mutable_capsule()->set_radius(c.radius);
      break;
    case Collider::Shape::kBox:
      *out.mutable_box()->mutable_center() = ToVec3(c.a);
      *out.mutable_box()->mutable_half_extents() = ToVec3(c.half_extents);
      break;
    case Collider::Shape::kPlane:
      *out.mutable_plane()->mutable_point() = ToVec3(c.a);
      *out.mutable_plane()->mutable_normal() = ToVec3(c.b);
      break;
    case Collider::Shape::kMesh: {
      const TriangleMesh mesh = ToMesh(c.mesh, fmt::format("colliders[{}].mesh", index));
      out = Guard([&] { return MeshCollider(mesh.vertices, mesh.faces); });
      break;
    }
  }
  return out;
}

Character FromCharacter(const v1::Character& c) {
  Character out;
  out.id = c.id();
  out.name = c.name();
  out.state = v1::CharacterState_Name(c.state());
  if (out.state.rfind("CHARACTER_STATE_", 0) == 0) out.state.erase(0, std::string_view("CHARACTER_STATE_").size());
  out.cache_hit = c.cache_hit();
  out.target_names.assign(c.target_names().begin(), c.target_names().end());
  out.combination_names.assign(c.combination_names().begin(), c.combination_names().end());
  const v1::RigSummary& s = c.summary();
  out.vertices = static_cast<int>(s.vertices());
  out.surface_vertices = static_cast<int>(s.surface_vertices());
  out.faces = static_cast<int>(s.faces());
  out.boundary_mode = s.boundary_mode();
  out.notes.assign(s.notes().begin(), s.notes().end());
  out.precompute_ms = s.precompute_ms();
  return out;
}

std::vector<float> Floats(const std::string& packed) {
  std::vector<float> out(packed.size() / sizeof(float));
  if (!out.empty()) std::memcpy(out.data(), packed.data(), out.size() * sizeof(float));
  return out;
}

}  // namespace

const char* Version() { return kVersion; }

Error::Error(std::string status, const std::string& message)
    : std::runtime_error(status + ": " + message), status_(std::move(status)) {}
Error::~Error() = default;

Collider Collider::Sphere(std::array<double, 3> centre, double radius) {
  Collider c;
  c.shape = Shape::kSphere, c.a = centre, c.radius = radius;
  return c;
}
Collider Collider::Capsule(std::array<double, 3> a, std::array<double, 3> b, double radius) {
  Collider c;
  c.shape = Shape::kCapsule, c.a = a, c.b = b, c.radius = radius;
  return c;
}
Collider Collider::Box(std::array<double, 3> centre, std::array<double, 3> half_extents) {
  Collider c;
  c.shape = Shape::kBox, c.a = centre, c.half_extents = half_extents;
  return c;
}
Collider Collider::Plane(std::array<double, 3> point, std::array<double, 3> normal) {
  Collider c;
  c.shape = Shape::kPlane, c.a = point, c.b = normal;
  return c;
}
Collider Collider::FromMesh(Mesh mesh) {
  Collider c;
  c.shape = Shape::kMesh, c.mesh = std::move(mesh);
  return c;
}

struct Client::Impl {
  springblend::Client client;
  std::map<std::string, std::vector<std::string>> names;  // character id -> its weight names

  const std::vector<std::string>& TargetNames(const std::string& id) {
    auto found = names.find(id);
    if (found == names.end()) {
      const v1::Character c = Guard([&] { return client.Get(id); });
      found = names.emplace(id, std::vector<std::string>(c.target_names().begin(), c.target_names().end())).first;
    }
    return found->second;
  }
};

namespace {

ClientOptions ToOptions(const Connection& c) {
  if (!(c.timeout_seconds > 0.0)) throw Invalid("Connection.timeout_seconds must be above 0");
  ClientOptions o;
  o.address = c.address;
  o.timeout = std::chrono::milliseconds(static_cast<long long>(std::min(c.timeout_seconds, 1e9) * 1000.0));
  o.token = c.token;
  o.tls = c.tls;
  o.tls_root_ca_file = c.tls_root_ca_file;
  o.tls_cert_file = c.tls_cert_file;
  o.tls_key_file = c.tls_key_file;
  o.tls_server_name = c.tls_server_name;
  return o;
}

}  // namespace

Client::Client(Connection connection)
    : impl_(Guard([&] { return std::make_unique<Impl>(Impl{springblend::Client(ToOptions(connection)), {}}); })) {}
Client::~Client() = default;
Client::Client(Client&&) noexcept = default;
Client& Client::operator=(Client&&) noexcept = default;

bool Client::Healthy() {
  return Guard([&] { return impl_->client.Healthy(); });
}

Character Client::Upload(const Mesh& rest, const std::vector<Target>& targets, const BuildOptions& options,
                         const std::string& name, const std::function<void(const BuildProgress&)>& on_progress) {
  const TriangleMesh rest_mesh = ToMesh(rest, "rest");
  std::vector<RigTarget> rig(targets.size());
  for (size_t t = 0; t < targets.size(); ++t) {
    const std::string what = fmt::format("targets[{}] ('{}')", t, targets[t].mesh.name);
    rig[t].mesh = ToMesh(targets[t].mesh, what);
    for (size_t i = 0; i < targets[t].inbetweens.size(); ++i) {
      rig[t].inbetweens.push_back({targets[t].inbetweens[i].weight,
                                   ToMesh(targets[t].inbetweens[i].mesh, fmt::format("{}.inbetweens[{}]", what, i))});
    }
    rig[t].mask = targets[t].mask;
    rig[t].combination = targets[t].combination;
  }
  v1::BuildOptions o;
  for (std::int32_t v : options.fixed_vertices) {
    if (v < 0) throw Invalid(fmt::format("fixed_vertices: {} is not a vertex", v));
    o.add_fixed_vertices(static_cast<std::uint32_t>(v));
  }
  o.set_static_tolerance(options.static_tolerance);
  o.set_bending_stiffness(options.bending_stiffness);
  o.set_no_interior(options.no_interior);
  o.set_no_anchor(options.no_anchor);
  o.set_no_target_paths(options.no_target_paths);
  o.set_hold_outer_rim(options.hold_outer_rim);
  if (options.path_intervals < 0) throw Invalid(fmt::format("path_intervals = {} is negative", options.path_intervals));
  if (options.path_max_samples < 0) {
    throw Invalid(fmt::format("path_max_samples = {} is negative", options.path_max_samples));
  }
  o.set_path_intervals(static_cast<std::uint32_t>(options.path_intervals));
  o.set_path_max_samples(static_cast<std::uint32_t>(options.path_max_samples));
  springblend::Client::UploadProgress progress;
  if (on_progress) {
    progress = [&](const std::string& id, const v1::BuildProgress& p) {
      on_progress({id, p.stage(), static_cast<int>(p.targets()), static_cast<int>(p.targets_done()), p.elapsed_ms(),
                   p.estimate_ms()});
    };
  }
  return FromCharacter(Guard([&] { return impl_->client.UploadRig(rest_mesh, rig, o, name, progress); }));
}

Character Client::Get(const std::string& id) {
  return FromCharacter(Guard([&] { return impl_->client.Get(id); }));
}

std::vector<Character> Client::List() {
  std::vector<Character> out;
  for (const v1::Character& c : Guard([&] { return impl_->client.List(); })) out.push_back(FromCharacter(c));
  return out;
}

void Client::Delete(const std::string& id) {
  Guard([&] { impl_->client.Delete(id); });
}

int Client::Solve(const std::string& character_id, const std::vector<Frame>& frames,
                  const std::vector<Collider>& colliders, const SolveOptions& options,
                  const std::function<void(const SolvedFrame&)>& on_frame) {
  v1::SolveRequest request;
  request.set_character_id(character_id);
  for (size_t c = 0; c < colliders.size(); ++c) *request.add_colliders() = ToCollider(colliders[c], c);
  for (size_t f = 0; f < frames.size(); ++f) {
    const Frame& frame = frames[f];
    v1::FrameRequest* out = request.add_frames();
    if (!frame.named_weights.empty()) {
      if (!frame.weights.empty()) {
        throw Invalid(fmt::format("frames[{}]: give weights or named_weights, not both", f));
      }
      std::vector<double> weights;
      if (const auto wrong = WeightsByName(frame.named_weights, impl_->TargetNames(character_id), &weights)) {
        throw Invalid(fmt::format("frames[{}].named_weights: {}", f, *wrong));
      }
      for (double w : weights) out->add_weights(w);
    } else {
      for (double w : frame.weights) out->add_weights(w);
    }
    for (const Transform& t : frame.collider_transforms) {
      v1::Transform* m = out->add_collider_transforms();
      *m->mutable_translation() = ToVec3(t.translation);
      m->set_qw(t.rotation[0]), m->set_qx(t.rotation[1]), m->set_qy(t.rotation[2]), m->set_qz(t.rotation[3]);
    }
    for (const Pin& p : frame.pins) {
      if (p.vertex < 0) throw Invalid(fmt::format("frames[{}].pins: {} is not a vertex", f, p.vertex));
      v1::Pin* pin = out->add_pins();
      pin->set_vertex(static_cast<std::uint32_t>(p.vertex));
      *pin->mutable_position() = ToVec3(p.position);
    }
  }
  request.mutable_options()->set_residual_tolerance(options.tolerance);
  request.mutable_options()->set_max_iterations(static_cast<std::uint32_t>(std::max(0, options.max_iterations)));
  request.mutable_options()->set_linear(options.linear);
  request.mutable_options()->set_with_normals(options.normals);
  request.mutable_options()->set_certify_minimum(options.certify_minimum);
  request.mutable_options()->set_mix(options.mix);
  if (options.linear_targets) {
    auto* names = request.mutable_options()->mutable_linear_targets()->mutable_names();
    for (const auto& name : *options.linear_targets) *names->Add() = name;
  }
  return Guard([&] {
    return impl_->client.Solve(request, [&](const v1::SolvedFrame& frame) {
      if (!on_frame) return;
      SolvedFrame out;
      out.index = static_cast<int>(frame.index());
      out.positions = Floats(frame.positions());
      out.normals = Floats(frame.normals());
      const v1::FrameSummary& s = frame.summary();
      out.converged = s.converged();
      out.termination = s.termination();
      out.message = s.message();
      out.newton_iterations = static_cast<int>(s.newton_iterations());
      out.contacts = static_cast<int>(s.contacts());
      out.residual = s.residual();
      out.solve_ms = s.solve_ms();
      out.finish = s.finish();
      out.minimum = s.minimum();
      on_frame(out);
    });
  });
}

}  // namespace springblend::sdk
