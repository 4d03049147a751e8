#include "convert.h"

#include <fmt/format.h>

#include <Eigen/Geometry>
#include <cstring>
#include <sstream>
#include <unordered_set>

#include "springblend/error.h"

namespace springblend::server {
namespace {

Eigen::Vector3d ToVector(const v1::Vec3& v) { return {v.x(), v.y(), v.z()}; }

[[noreturn]] void Invalid(const std::string& what) { throw Error(ErrorCode::kInvalidInput, what); }

}  // namespace

void UploadAssembler::Fail(const std::string& what, bool limit) {
  over_limit_ = limit;
  Invalid(what);
}

void UploadAssembler::Add(const v1::UploadChunk& chunk) {
  bytes_ += static_cast<std::int64_t>(chunk.ByteSizeLong());
  if (bytes_ > limits_.max_upload_bytes) {
    Fail(fmt::format("the upload is over the limit of {} bytes (--max-upload-bytes)", limits_.max_upload_bytes), true);
  }
  if (chunk.has_header()) {
    if (have_header_) Fail("a second upload header; send exactly one, first");
    const v1::UploadHeader& h = chunk.header();
    if (h.name().size() > 256) Fail("header.name is longer than 256 bytes");
    if (h.vertex_count() < 3) Fail(fmt::format("header.vertex_count = {}: a mesh needs at least 3 vertices", h.vertex_count()));
    if (h.vertex_count() > static_cast<std::uint32_t>(limits_.max_vertices)) {
      Fail(fmt::format("header.vertex_count = {} is over the limit of {} (--max-vertices)", h.vertex_count(), limits_.max_vertices), true);
    }
    if (h.face_count() < 1) Fail("header.face_count = 0: a mesh needs faces");
    if (h.face_count() > 4u * static_cast<std::uint32_t>(limits_.max_vertices)) Fail("header.face_count is over the limit", true);
    if (h.target_names_size() < 1) Fail("header.target_names is empty: a character needs at least one target");
    if (h.target_names_size() > limits_.max_targets) {
      Fail(fmt::format("{} targets is over the limit of {}", h.target_names_size(), limits_.max_targets), true);
    }
    const std::int64_t expected = 12LL * h.face_count() + 24LL * h.vertex_count() * (h.target_names_size() + 1);
    if (expected > limits_.max_upload_bytes) {
      Fail(fmt::format("the character needs {} bytes, over the limit of {} (--max-upload-bytes)", expected, limits_.max_upload_bytes), true);
    }
    std::unordered_set<std::string> names;
    for (int t = 0; t < h.target_names_size(); ++t) {
      if (h.target_names(t).empty()) Fail(fmt::format("header.target_names[{}] is empty", t));
      if (!names.insert(h.target_names(t)).second) Fail(fmt::format("header.target_names[{}] '{}' is used twice", t, h.target_names(t)));
      data_.target_names.push_back(h.target_names(t));
    }
    data_.name = h.name();
    const v1::BuildOptions& o = h.options();
    for (auto v : o.fixed_vertices()) {
      if (v >= h.vertex_count()) Fail(fmt::format("options.fixed_vertices: {} is not a vertex (there are {})", v, h.vertex_count()));
      data_.options.fixed_vertices.push_back(static_cast<int>(v));
    }
    if (o.static_tolerance() != 0.0) data_.options.static_tolerance = o.static_tolerance();
    data_.options.interior = !o.no_interior();
    data_.options.anchor = !o.no_anchor();
    if (o.bending_stiffness() != 0.0) data_.options.bending_stiffness = o.bending_stiffness();
    data_.options.Validate();
    data_.faces.resize(h.face_count(), 3);
    data_.shapes.assign(static_cast<size_t>(h.target_names_size()) + 1, Points(h.vertex_count(), 3));
    filled_.assign(data_.shapes.size() + 1, {});
    filled_[0].assign(h.face_count(), 0);
    for (size_t s = 1; s < filled_.size(); ++s) filled_[s].assign(h.vertex_count(), 0);
    have_header_ = true;
    return;
  }
  if (!chunk.has_piece()) Fail("an upload chunk with neither header nor piece");
  if (!have_header_) Fail("a mesh piece before the header; send the header first");
  const v1::MeshPiece& p = chunk.piece();
  const std::string& bytes = p.data();
  size_t array = 0;
  size_t element_bytes = 1;  // every branch below sets these or throws
  char* target = nullptr;
  size_t elements = 0;
  if (p.kind() == v1::MeshPiece::FACES) {
    array = 0;
    element_bytes = 12;
    elements = filled_[0].size();
    target = reinterpret_cast<char*>(data_.faces.data());
  } else if (p.kind() == v1::MeshPiece::POSITIONS) {
    if (p.shape() >= data_.shapes.size()) {
      Fail(fmt::format("piece.shape = {} but there are {} shapes (rest + targets)", p.shape(), data_.shapes.size()));
    }
    array = p.shape() + 1;
    element_bytes = 24;
    elements = filled_[array].size();
    target = reinterpret_cast<char*>(data_.shapes[p.shape()].data());
  } else {
    Fail("piece.kind must be FACES or POSITIONS");
  }
  if (bytes.size() % element_bytes != 0) {
    Fail(fmt::format("a {} piece has {} bytes, not a multiple of {}", p.kind() == v1::MeshPiece::FACES ? "FACES" : "POSITIONS", bytes.size(), element_bytes));
  }
  const size_t count = bytes.size() / element_bytes;
  if (p.offset() > elements || count > elements - p.offset()) {
    Fail(fmt::format("a piece covers elements {}..{} but the array has {}", p.offset(), p.offset() + count, elements));
  }
  for (size_t i = p.offset(); i < p.offset() + count; ++i) {
    if (filled_[array][i]) Fail(fmt::format("pieces overlap at element {}", i));
    filled_[array][i] = 1;
  }
  // Row-major Eigen storage matches the wire's packed triples (both little-endian on our targets).
  std::memcpy(target + p.offset() * element_bytes, bytes.data(), bytes.size());
}

CharacterData UploadAssembler::Finish() {
  if (!have_header_) Fail("the upload ended without a header");
  for (size_t a = 0; a < filled_.size(); ++a) {
    for (size_t i = 0; i < filled_[a].size(); ++i) {
      if (!filled_[a][i]) {
        Fail(a == 0 ? fmt::format("the upload ended with face {} missing", i)
                    : fmt::format("the upload ended with vertex {} of shape {} missing", i, a - 1));
      }
    }
  }
  return std::move(data_);
}

v1::Character ToProto(const CharacterStore::Entry& entry, bool cache_hit) {
  v1::Character c;
  c.set_id(entry.id);
  c.set_name(entry.name);
  c.set_cache_hit(cache_hit);
  for (const auto& t : entry.rig->target_names()) c.add_target_names(t);
  const RigSummary& s = entry.rig->summary();
  v1::RigSummary* out = c.mutable_summary();
  out->set_surface_vertices(s.surface_vertices);
  out->set_vertices(s.vertices);
  out->set_faces(s.faces);
  out->set_springs(s.springs);
  out->set_structure_springs(s.springs_by_kind[static_cast<int>(SpringKind::kStructure)]);
  out->set_bending_springs(s.springs_by_kind[static_cast<int>(SpringKind::kBending)]);
  out->set_internal_springs(s.springs_by_kind[static_cast<int>(SpringKind::kInternal)]);
  out->set_tetrahedra(s.tetrahedra);
  out->set_interior_vertices(s.interior_vertices);
  out->set_anchor_vertices(s.anchor_vertices);
  out->set_static_vertices(s.static_vertices);
  out->set_interior(s.interior);
  out->set_interior_reason(s.interior_reason);
  out->set_boundary_mode(ToString(s.boundary_mode));
  out->set_precompute_ms(s.precompute_ms);
  for (const auto& n : s.notes) out->add_notes(n);
  return c;
}

SolveJob ToSolveJob(const v1::SolveRequest& request, const Rig& rig, const Limits& limits) {
  SolveJob job;
  if (request.frames_size() == 0) Invalid("frames is empty: send at least one frame");
  if (request.frames_size() > limits.max_frames) {
    throw Error(ErrorCode::kInvalidInput, fmt::format("{} frames is over the limit of {} (--max-frames)", request.frames_size(), limits.max_frames));
  }
  const v1::SolveOptions& o = request.options();
  if (o.residual_tolerance() != 0.0) job.options.residual_tolerance = o.residual_tolerance();
  if (o.max_iterations() != 0) job.options.max_iterations = static_cast<int>(std::min<std::uint32_t>(o.max_iterations(), 1'000'000));
  job.options.linear = o.linear();
  job.with_normals = o.with_normals();
  try {
    job.options.Validate();
  } catch (const Error& e) {
    Invalid(std::string("options: ") + e.what());
  }
  for (int i = 0; i < request.colliders_size(); ++i) {
    const v1::Collider& c = request.colliders(i);
    try {
      switch (c.shape_case()) {
        case v1::Collider::kSphere:
          job.colliders.push_back(Collider::Sphere(ToVector(c.sphere().center()), c.sphere().radius()));
          break;
        case v1::Collider::kCapsule:
          job.colliders.push_back(Collider::Capsule(ToVector(c.capsule().a()), ToVector(c.capsule().b()), c.capsule().radius()));
          break;
        case v1::Collider::kBox:
          job.colliders.push_back(Collider::Box(ToVector(c.box().center()), ToVector(c.box().half_extents())));
          break;
        case v1::Collider::kPlane:
          job.colliders.push_back(Collider::Plane(ToVector(c.plane().point()), ToVector(c.plane().normal())));
          break;
        case v1::Collider::kMeshObj: {
          TriangleMesh mesh = LoadMeshFromText(c.mesh_obj(), "obj", fmt::format("colliders[{}].mesh_obj", i));
          job.colliders.push_back(Collider::Mesh(mesh));
          break;
        }
        case v1::Collider::SHAPE_NOT_SET:
          Invalid("no shape set");
      }
    } catch (const Error& e) {
      Invalid(fmt::format("colliders[{}]: {}", i, e.what()));
    }
  }
  for (int f = 0; f < request.frames_size(); ++f) {
    const v1::FrameRequest& in = request.frames(f);
    Frame frame;
    frame.weights.assign(in.weights().begin(), in.weights().end());
    for (const auto& t : in.collider_transforms()) {
      RigidTransform motion;
      motion.translation = ToVector(t.translation());
      if (t.qw() != 0.0 || t.qx() != 0.0 || t.qy() != 0.0 || t.qz() != 0.0) {
        motion.rotation = Eigen::Quaterniond(t.qw(), t.qx(), t.qy(), t.qz());
        if (!(motion.rotation.norm() > 0.0) || !motion.rotation.coeffs().allFinite()) {
          Invalid(fmt::format("frames[{}].collider_transforms: not a finite quaternion", f));
        }
        motion.rotation.normalize();
      }
      frame.collider_transforms.push_back(motion);
    }
    for (const auto& p : in.pins()) {
      if (p.vertex() >= static_cast<std::uint32_t>(rig.num_surface_vertices())) {
        Invalid(fmt::format("frames[{}].pins: vertex {} is not a vertex of the mesh (it has {})", f, p.vertex(), rig.num_surface_vertices()));
      }
      frame.pins.push_back({static_cast<int>(p.vertex()), ToVector(p.position())});
    }
    try {
      ValidateFrame(rig, frame, job.colliders.size());
    } catch (const Error& e) {
      Invalid(fmt::format("frames[{}]: {}", f, e.what()));
    }
    job.frames.push_back(std::move(frame));
  }
  return job;
}

v1::SolvedFrame ToProto(int index, const Points& positions, const Faces& faces, const SolveSummary& summary,
                        bool with_normals, const std::string& served_by) {
  v1::SolvedFrame out;
  out.set_index(static_cast<std::uint32_t>(index));
  const Eigen::Matrix<float, Eigen::Dynamic, 3, Eigen::RowMajor> p = positions.cast<float>();
  out.set_positions(reinterpret_cast<const char*>(p.data()), sizeof(float) * static_cast<size_t>(p.size()));
  if (with_normals) {
    Points normals = Points::Zero(positions.rows(), 3);
    for (Eigen::Index f = 0; f < faces.rows(); ++f) {
      const Eigen::RowVector3d a = positions.row(faces(f, 0)), b = positions.row(faces(f, 1)), c = positions.row(faces(f, 2));
      const Eigen::RowVector3d n = (b - a).cross(c - a);  // area-weighted
      for (int k = 0; k < 3; ++k) normals.row(faces(f, k)) += n;
    }
    normals.rowwise().normalize();
    const Eigen::Matrix<float, Eigen::Dynamic, 3, Eigen::RowMajor> nf = normals.cast<float>();
    out.set_normals(reinterpret_cast<const char*>(nf.data()), sizeof(float) * static_cast<size_t>(nf.size()));
  }
  v1::FrameSummary* s = out.mutable_summary();
  s->set_converged(summary.converged());
  s->set_termination(ToString(summary.termination));
  s->set_message(summary.message);
  s->set_newton_iterations(summary.newton_iterations);
  s->set_factorizations(summary.factorizations);
  s->set_residual(summary.residual);
  s->set_contacts(summary.contacts);
  s->set_contact_rounds(summary.contact_rounds);
  s->set_pins(summary.pins);
  s->set_inverted_tetrahedra(summary.inverted_tetrahedra);
  s->set_solve_ms(summary.solve_ms);
  s->set_served_by(served_by);
  return out;
}

}  // namespace springblend::server
