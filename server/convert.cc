#include "convert.h"

#include <fmt/format.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstring>
#include <iterator>
#include <limits>
#include <sstream>
#include <unordered_set>

#include "springblend/error.h"
#include "status.h"

namespace springblend::server {
namespace {

Eigen::Vector3d ToVector(const v1::Vec3& v) { return {v.x(), v.y(), v.z()}; }

[[noreturn]] void Invalid(const std::string& what) { throw Error(ErrorCode::kInvalidInput, what); }

// Answers go out as float32, and coordinates add up (a collider's centre, its radius and its frame's
// translation): a double that is finite but beyond float32 (1e308) or near its end came back as inf.
// Coordinates, radii and extents are bounded well inside float32; non-finite ones are left to the solver's
// checks (which name them in their own words).
constexpr double kMaxCoordinate = 1e12;
// The target paths' density an upload may ask for (BuildOptions): a path's memory grows with its samples and
// its build with its steps, so the wire's bounds are tighter than RigOptions'.
constexpr std::uint32_t kMinPathIntervals = 4, kMaxPathIntervals = 128;
constexpr std::uint32_t kMinPathMaxSamples = 8, kMaxPathMaxSamples = 256;

void CheckMagnitude(double value, const std::function<std::string()>& field) {
  if (!std::isfinite(value)) return;
  if (std::abs(value) > std::numeric_limits<float>::max()) {
    Invalid(fmt::format("{} = {} is not a finite float32", field(), value));
  }
  if (std::abs(value) > kMaxCoordinate) {
    Invalid(fmt::format("{} = {} is beyond +-{:g}, the largest coordinate or size a solve takes (answers are float32)",
                        field(), value, kMaxCoordinate));
  }
}

void CheckMagnitude(const v1::Vec3& v, const std::string& field) {
  CheckMagnitude(v.x(), [&] { return field + ".x"; });
  CheckMagnitude(v.y(), [&] { return field + ".y"; });
  CheckMagnitude(v.z(), [&] { return field + ".z"; });
}

// Every vertex of a mesh (a collider's, or an uploaded shape) within kMaxCoordinate.
void CheckMagnitude(const Points& points, const std::string& field) {
  for (Eigen::Index v = 0; v < points.rows(); ++v) {
    for (int c = 0; c < 3; ++c) {
      CheckMagnitude(points(v, c), [&] { return fmt::format("{} vertex {} {}", field, v, "xyz"[c]); });
    }
  }
}

// A collider's own numbers, before it is built: "colliders[2].sphere.radius = 1e+200 is not a finite float32".
void CheckColliderMagnitudes(const v1::Collider& c, int i) {
  const std::string at = fmt::format("colliders[{}]", i);
  switch (c.shape_case()) {
    case v1::Collider::kSphere:
      CheckMagnitude(c.sphere().center(), at + ".sphere.center");
      CheckMagnitude(c.sphere().radius(), [&] { return at + ".sphere.radius"; });
      break;
    case v1::Collider::kCapsule:
      CheckMagnitude(c.capsule().a(), at + ".capsule.a");
      CheckMagnitude(c.capsule().b(), at + ".capsule.b");
      CheckMagnitude(c.capsule().radius(), [&] { return at + ".capsule.radius"; });
      break;
    case v1::Collider::kBox:
      CheckMagnitude(c.box().center(), at + ".box.center");
      CheckMagnitude(c.box().half_extents(), at + ".box.half_extents");
      break;
    case v1::Collider::kPlane:
      // The normal is normalized (the solver refuses one whose length overflows); only the point is a position.
      CheckMagnitude(c.plane().point(), at + ".plane.point");
      break;
    default:
      break;  // meshes: checked vertex by vertex once read
  }
}

// A mesh collider's arrays as a mesh, checked element by element so a refusal names the array and the index
// (`mesh.triangles[5]`; the caller prefixes the collider). Counts are checked against the limits from the byte
// sizes, before anything is allocated. Collider::Mesh then checks that it is closed and has volume.
TriangleMesh MeshFromArrays(const v1::MeshArrays& arrays, int collider, const MeshColliderLimits& limits) {
  const std::string& positions = arrays.positions();
  const std::string& triangles = arrays.triangles();
  if (positions.size() % 24 != 0) {
    Invalid(fmt::format("mesh.positions has {} bytes, not a multiple of 24 (float64 x y z per vertex)", positions.size()));
  }
  if (triangles.size() % 12 != 0) {
    Invalid(fmt::format("mesh.triangles has {} bytes, not a multiple of 12 (int32 a b c per triangle)", triangles.size()));
  }
  const size_t n = positions.size() / 24, m = triangles.size() / 12;
  const auto over = [&](const char* array, size_t count, int limit, const char* what) {
    if (limit > 0 && count > static_cast<size_t>(limit)) {
      throw LimitError(fmt::format("colliders[{}].mesh.{} has {} {}, over the limit of {} (--max-collider-faces)",
                                   collider, array, count, what, limit));
    }
  };
  over("positions", n, limits.max_vertices, "vertices");
  over("triangles", m, limits.max_faces, "triangles");
  if (n < 4 || m < 4) {
    Invalid(fmt::format("mesh has {} vertices and {} triangles: a closed mesh needs at least 4 of each", n, m));
  }
  TriangleMesh mesh;
  mesh.name = mesh.source = "mesh";
  // Row-major Eigen storage matches the wire's packed triples (both little-endian on our targets).
  mesh.vertices.resize(static_cast<Eigen::Index>(n), 3);
  std::memcpy(mesh.vertices.data(), positions.data(), positions.size());
  mesh.faces.resize(static_cast<Eigen::Index>(m), 3);
  std::memcpy(mesh.faces.data(), triangles.data(), triangles.size());
  for (Eigen::Index v = 0; v < mesh.vertices.rows(); ++v) {
    for (int c = 0; c < 3; ++c) {
      if (!std::isfinite(mesh.vertices(v, c))) {
        Invalid(fmt::format("mesh.positions: vertex {} has a non-finite {} coordinate ({})", v, "xyz"[c],
                            mesh.vertices(v, c)));
      }
    }
  }
  CheckMagnitude(mesh.vertices, "mesh.positions:");
  for (Eigen::Index f = 0; f < mesh.faces.rows(); ++f) {
    for (int c = 0; c < 3; ++c) {
      const int v = mesh.faces(f, c);
      if (v < 0 || static_cast<size_t>(v) >= n) {
        Invalid(fmt::format("mesh.triangles[{}] refers to vertex {}, but mesh.positions has {} vertices", f, v, n));
      }
      if (v == mesh.faces(f, (c + 1) % 3)) Invalid(fmt::format("mesh.triangles[{}] repeats vertex {}", f, v));
    }
  }
  return mesh;
}

// The solver's in-between rule, checked on the header so a bad rig is refused before its meshes arrive.
void CheckInbetweenWeights(const std::vector<double>& weights, int t, const std::string& name) {
  try {
    ValidateInbetweenWeights(weights, [](size_t i) { return fmt::format("inbetween_weights[{}]", i); });
  } catch (const Error& e) {
    Invalid(fmt::format("header.targets[{}] (target '{}'): {}", t, Printable(name), e.what()));
  }
}

}  // namespace

void UploadAssembler::Fail(const std::string& what, bool limit) {
  if (limit) throw LimitError(what);
  Invalid(what);
}

void CheckId(const std::string& id, const char* field) {
  if (CharacterStore::ValidId(id)) return;
  Invalid(fmt::format("{} '{}'{} is not a character id: ids are 64 lowercase hex digits (SHA-256), as "
                      "UploadCharacter returns them",
                      field, Printable(id, 16), id.size() > 16 ? fmt::format(" ({} bytes)", id.size()) : ""));
}

std::string Printable(std::string_view text, size_t max) {
  std::string out;
  for (size_t i = 0; i < text.size(); ++i) {
    if (out.size() >= max) {
      out += "...";
      break;
    }
    const unsigned char c = static_cast<unsigned char>(text[i]);
    if (c == '\\') {
      out += "\\\\";
    } else if (c < 0x20 || c == 0x7f) {
      out += fmt::format("\\x{:02x}", c);
    } else {
      out += static_cast<char>(c);
    }
  }
  return out;
}

void UploadAssembler::Add(v1::UploadChunk& chunk) {
  const std::int64_t size = static_cast<std::int64_t>(chunk.ByteSizeLong());
  bytes_ += size;
  if (bytes_ > limits_.max_upload_bytes) {
    Fail(fmt::format("the upload is over the limit of {} bytes (--max-upload-bytes)", limits_.max_upload_bytes), true);
  }
  // Held twice at most: as received, and while Finish assembles the arrays.
  memory_.Grow(2 * size);
  if (chunk.has_header()) {
    if (have_header_) Fail("a second upload header; send exactly one, first");
    const v1::UploadHeader& h = chunk.header();
    if (h.name().size() > limits_.max_name_bytes) Fail(fmt::format("header.name is longer than {} bytes", limits_.max_name_bytes));
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
    if (h.targets_size() != 0 && h.targets_size() != h.target_names_size()) {
      Fail(fmt::format("header.targets has {} entries: send none, or one per target_names entry ({})", h.targets_size(),
                       h.target_names_size()));
    }
    size_t inbetweens = 0, masks = 0;
    for (const v1::TargetRig& t : h.targets()) {
      inbetweens += static_cast<size_t>(t.inbetween_weights_size());
      masks += t.has_mask() ? 1 : 0;
    }
    if (inbetweens > static_cast<size_t>(limits_.max_targets)) {
      Fail(fmt::format("{} in-betweens is over the limit of {}", inbetweens, limits_.max_targets), true);
    }
    const std::int64_t expected = 12LL * h.face_count() +
                                  24LL * h.vertex_count() * (h.target_names_size() + 1 + static_cast<std::int64_t>(inbetweens)) +
                                  8LL * h.vertex_count() * static_cast<std::int64_t>(masks);
    if (expected > limits_.max_upload_bytes) {
      Fail(fmt::format("the character needs {} bytes, over the limit of {} (--max-upload-bytes)", expected, limits_.max_upload_bytes), true);
    }
    std::unordered_set<std::string> names;
    for (int t = 0; t < h.target_names_size(); ++t) {
      const std::string& name = h.target_names(t);
      if (name.empty()) Fail(fmt::format("header.target_names[{}] is empty", t));
      if (name.size() > limits_.max_name_bytes) {
        Fail(fmt::format("header.target_names[{}] '{}' is {} bytes, over the limit of {}", t, Printable(name, 32),
                         name.size(), limits_.max_name_bytes));
      }
      if (!names.insert(name).second) Fail(fmt::format("header.target_names[{}] '{}' is used twice", t, Printable(name)));
      data_.target_names.push_back(name);
    }
    // The rig's own rules (weights in (0, 1), drivers that exist) are the solver's to check, naming the target.
    for (int t = 0; t < h.targets_size(); ++t) {
      const v1::TargetRig& in = h.targets(t);
      TargetRigData rig;
      rig.inbetween_weights.assign(in.inbetween_weights().begin(), in.inbetween_weights().end());
      CheckInbetweenWeights(rig.inbetween_weights, t, data_.target_names[static_cast<size_t>(t)]);
      for (int d = 0; d < in.combination_size(); ++d) {
        if (in.combination(d).size() > limits_.max_name_bytes) {
          Fail(fmt::format("header.targets[{}].combination[{}] is over {} bytes", t, d, limits_.max_name_bytes));
        }
        rig.combination.push_back(in.combination(d));
      }
      if (in.combination_size() > h.target_names_size()) {
        Fail(fmt::format("header.targets[{}].combination has more drivers than there are targets", t));
      }
      if (in.has_mask()) mask_owner_.push_back(static_cast<std::uint32_t>(t));
      data_.target_rigs.push_back(std::move(rig));
    }
    data_.name = h.name();
    const v1::BuildOptions& o = h.options();
    if (o.fixed_vertices_size() > static_cast<int>(h.vertex_count())) Fail("options.fixed_vertices has more entries than vertices");
    for (auto v : o.fixed_vertices()) {
      if (v >= h.vertex_count()) Fail(fmt::format("options.fixed_vertices: {} is not a vertex (there are {})", v, h.vertex_count()));
      data_.options.fixed_vertices.push_back(static_cast<int>(v));
    }
    if (o.static_tolerance() != 0.0) data_.options.static_tolerance = o.static_tolerance();
    data_.options.interior = !o.no_interior();
    data_.options.anchor = !o.no_anchor();
    data_.options.target_paths = !o.no_target_paths();
    data_.options.hold_outer_rim = o.hold_outer_rim();
    if (o.bending_stiffness() != 0.0) data_.options.bending_stiffness = o.bending_stiffness();
    const auto density = [&](std::uint32_t value, std::uint32_t low, std::uint32_t high, const char* field, int* out) {
      if (value == 0) return;
      if (value < low || value > high) Fail(fmt::format("options.{} = {} is outside [{}, {}]", field, value, low, high));
      *out = static_cast<int>(value);
    };
    density(o.path_intervals(), kMinPathIntervals, kMaxPathIntervals, "path_intervals", &data_.options.path_intervals);
    density(o.path_max_samples(), kMinPathMaxSamples, kMaxPathMaxSamples, "path_max_samples",
            &data_.options.path_max_samples);
    data_.options.Validate();
    vertex_count_ = h.vertex_count();
    face_count_ = h.face_count();
    shapes_ = static_cast<size_t>(h.target_names_size()) + 1 + inbetweens;
    covered_.assign(1 + shapes_ + mask_owner_.size(), {});
    have_header_ = true;
    return;
  }
  if (!chunk.has_piece()) Fail("an upload chunk with neither header nor piece");
  if (!have_header_) Fail("a mesh piece before the header; send the header first");
  v1::MeshPiece& p = *chunk.mutable_piece();
  size_t array = 0;
  size_t element_bytes = 1;  // every branch below sets these or throws
  size_t elements = 0;
  if (p.kind() == v1::MeshPiece::FACES) {
    array = 0;
    element_bytes = 12;
    elements = face_count_;
  } else if (p.kind() == v1::MeshPiece::POSITIONS) {
    if (p.shape() >= shapes_) {
      Fail(fmt::format("piece.shape = {} but there are {} shapes (rest + targets + in-betweens)", p.shape(), shapes_));
    }
    array = p.shape() + 1;
    element_bytes = 24;
    elements = vertex_count_;
  } else if (p.kind() == v1::MeshPiece::MASK) {
    const auto owner = std::find(mask_owner_.begin(), mask_owner_.end(), p.shape());
    if (owner == mask_owner_.end()) {
      Fail(fmt::format("a MASK piece for target {}, which header.targets does not give a mask (has_mask)", p.shape()));
    }
    array = 1 + shapes_ + static_cast<size_t>(owner - mask_owner_.begin());
    element_bytes = 8;
    elements = vertex_count_;
  } else {
    Fail("piece.kind must be FACES, POSITIONS or MASK");
  }
  const size_t byte_count = p.data().size();
  if (byte_count % element_bytes != 0) {
    Fail(fmt::format("a {} piece has {} bytes, not a multiple of {}", v1::MeshPiece::Kind_Name(p.kind()), byte_count,
                     element_bytes));
  }
  const size_t count = byte_count / element_bytes;
  if (p.offset() > elements || count > elements - p.offset()) {
    Fail(fmt::format("a piece covers elements {}..{} but the array has {}", p.offset(), p.offset() + count, elements));
  }
  if (count == 0) return;
  // Ranges kept disjoint and merged with their neighbours, so a mesh sent in order is one range.
  std::map<size_t, size_t>& ranges = covered_[array];
  size_t first = p.offset(), end = p.offset() + count;
  auto next = ranges.upper_bound(first);
  if (next != ranges.begin()) {
    auto previous = std::prev(next);
    if (previous->second > first) Fail(fmt::format("pieces overlap at element {}", first));
    if (previous->second == first) {
      first = previous->first;
      ranges.erase(previous);
    }
  }
  if (next != ranges.end()) {
    if (next->first < end) Fail(fmt::format("pieces overlap at element {}", next->first));
    if (next->first == end) {
      end = next->second;
      ranges.erase(next);
    }
  }
  ranges[first] = end;
  pieces_.push_back({array, static_cast<size_t>(p.offset()), std::move(*p.mutable_data())});
}

CharacterData UploadAssembler::Finish() {
  if (!have_header_) Fail("the upload ended without a header");
  for (size_t a = 0; a < covered_.size(); ++a) {
    const size_t elements = a == 0 ? face_count_ : vertex_count_;
    const auto& ranges = covered_[a];
    const size_t missing = ranges.empty() || ranges.begin()->first != 0 ? 0 : ranges.begin()->second;
    if (missing < elements) {
      Fail(a == 0         ? fmt::format("the upload ended with face {} missing", missing)
           : a <= shapes_ ? fmt::format("the upload ended with vertex {} of shape {} missing", missing, a - 1)
                          : fmt::format("the upload ended with value {} of target {}'s mask missing", missing,
                                        mask_owner_[a - 1 - shapes_]));
    }
  }
  data_.faces.resize(face_count_, 3);
  std::vector<Points> shapes(shapes_, Points(vertex_count_, 3));
  std::vector<std::vector<double>> masks(mask_owner_.size(), std::vector<double>(vertex_count_));
  for (Piece& piece : pieces_) {
    // Row-major Eigen storage matches the wire's packed triples (both little-endian on our targets).
    char* target = piece.array == 0         ? reinterpret_cast<char*>(data_.faces.data())
                   : piece.array <= shapes_ ? reinterpret_cast<char*>(shapes[piece.array - 1].data())
                                            : reinterpret_cast<char*>(masks[piece.array - 1 - shapes_].data());
    const size_t element_bytes = piece.array == 0 ? 12 : piece.array <= shapes_ ? 24 : 8;
    std::memcpy(target + piece.offset * element_bytes, piece.bytes.data(), piece.bytes.size());
    std::string().swap(piece.bytes);
  }
  pieces_.clear();
  // Coordinates well inside float32 (answers are float32; an uploaded 1e300 came back as inf). Non-finite
  // values, and masks beyond the weights' bound, are the solver's to refuse (Rig::Build).
  for (size_t k = 0; k < shapes.size(); ++k) {
    CheckMagnitude(shapes[k], k == 0 ? std::string("the rest shape:") : fmt::format("shape {}:", k));
  }
  // Shapes past the targets are the in-betweens, target by target.
  const size_t targets = data_.target_names.size();
  data_.shapes.assign(std::make_move_iterator(shapes.begin()), std::make_move_iterator(shapes.begin() + 1 + targets));
  size_t next = 1 + targets;
  for (TargetRigData& rig : data_.target_rigs) {
    for (size_t i = 0; i < rig.inbetween_weights.size(); ++i) rig.inbetweens.push_back(std::move(shapes[next++]));
  }
  for (size_t k = 0; k < mask_owner_.size(); ++k) data_.target_rigs[mask_owner_[k]].mask = std::move(masks[k]);
  // Every target plain: the same character (and id) as an upload without header.targets.
  if (std::all_of(data_.target_rigs.begin(), data_.target_rigs.end(), [](const TargetRigData& t) {
        return t.inbetween_weights.empty() && t.mask.empty() && t.combination.empty();
      })) {
    data_.target_rigs.clear();
  }
  return std::move(data_);
}

v1::Character ToProto(const CharacterStore::PendingBuild& build) {
  v1::Character c;
  c.set_id(build.id());
  c.set_name(build.name());
  c.set_state(v1::CHARACTER_STATE_BUILDING);
  const BuildProgress p = build.progress();
  v1::BuildProgress* out = c.mutable_build();
  out->set_stage(p.rig.stage);
  out->set_targets(static_cast<std::uint32_t>(p.rig.targets));
  out->set_targets_done(static_cast<std::uint32_t>(p.rig.targets_done));
  out->set_path_samples(static_cast<std::uint32_t>(p.rig.samples_done));
  out->set_elapsed_ms(p.rig.elapsed_ms);
  out->set_estimate_ms(p.estimate_ms);
  out->set_from_cache_file(p.from_file);
  return c;
}

v1::Character ToProto(const CharacterStore::Entry& entry, bool cache_hit) {
  v1::Character c;
  c.set_id(entry.id);
  c.set_state(v1::CHARACTER_STATE_READY);
  c.set_name(entry.name);
  c.set_cache_hit(cache_hit);
  for (const auto& t : entry.rig->target_names()) c.add_target_names(t);
  for (const auto& t : entry.rig->combination_names()) c.add_combination_names(t);
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
  if (!entry.not_persisted.empty()) {
    out->add_notes("not persisted: " + entry.not_persisted +
                   "; served from this server's memory only, unknown to a restart or another replica");
  }
  out->set_rim_vertices(static_cast<std::uint32_t>(s.rim_vertices));
  out->set_paths_loaded(s.paths_loaded);
  out->set_path_samples(s.path_samples);
  out->set_uncertified_path_intervals(s.uncertified_path_intervals);
  out->set_path_max_error(s.path_max_error);
  out->set_path_ms(s.path_ms);
  out->set_path_bytes(static_cast<std::uint64_t>(s.path_bytes));
  out->set_path_file_bytes(static_cast<std::uint64_t>(s.path_file_bytes));
  out->set_rig_bytes(static_cast<std::uint64_t>(s.rig_bytes));
  for (const auto& path : s.paths) {
    v1::TargetPathSummary* p = out->add_paths();
    p->set_target(path.target);
    p->set_samples(static_cast<std::uint32_t>(path.samples));
    p->set_solves(static_cast<std::uint32_t>(path.solves));
    p->set_uncertified(static_cast<std::uint32_t>(path.uncertified));
    p->set_max_error(path.max_error);
    p->set_ms(path.ms);
    p->set_checks(static_cast<std::uint32_t>(path.checks));
    p->set_local_checks(static_cast<std::uint32_t>(path.local_checks));
    for (const auto& [from, to] : path.uncertified_ranges) {
      v1::WeightRange* range = p->add_uncertified_ranges();
      range->set_low(from);
      range->set_high(to);
    }
  }
  return c;
}

void ToOptions(const v1::SolveOptions& o, SolveJob* job) {
  if (o.residual_tolerance() != 0.0) job->options.residual_tolerance = o.residual_tolerance();
  if (o.max_iterations() != 0) job->options.max_iterations = static_cast<int>(std::min<std::uint32_t>(o.max_iterations(), 1'000'000));
  job->options.linear = o.linear();
  job->with_normals = o.with_normals();
  job->options.certify_minimum = o.certify_minimum();
  try {
    if (!o.mix().empty()) job->options.mix = MixModelFromString(o.mix());
    if (o.has_linear_targets()) {
      job->options.linear_targets = std::vector<std::string>(o.linear_targets().names().begin(),
                                                             o.linear_targets().names().end());
    }
    job->options.Validate();
  } catch (const Error& e) {
    Invalid(std::string("options: ") + e.what());
  }
}

std::vector<Collider> ToColliders(const google::protobuf::RepeatedPtrField<v1::Collider>& colliders,
                                  const Limits& limits, const std::function<bool()>& stopped) {
  if (colliders.size() > limits.max_colliders) {
    throw LimitError(fmt::format("{} colliders is over the limit of {}", colliders.size(), limits.max_colliders));
  }
  std::vector<Collider> out;
  for (int i = 0; i < colliders.size(); ++i) {
    if (stopped && stopped()) throw CancelledError(fmt::format("stopped while converting colliders[{}]", i));
    const v1::Collider& c = colliders[i];
    CheckColliderMagnitudes(c, i);
    try {
      switch (c.shape_case()) {
        case v1::Collider::kSphere:
          out.push_back(Collider::Sphere(ToVector(c.sphere().center()), c.sphere().radius()));
          break;
        case v1::Collider::kCapsule:
          out.push_back(Collider::Capsule(ToVector(c.capsule().a()), ToVector(c.capsule().b()), c.capsule().radius()));
          break;
        case v1::Collider::kBox:
          out.push_back(Collider::Box(ToVector(c.box().center()), ToVector(c.box().half_extents())));
          break;
        case v1::Collider::kPlane:
          out.push_back(Collider::Plane(ToVector(c.plane().point()), ToVector(c.plane().normal())));
          break;
        case v1::Collider::kMeshObj: {
          const TriangleMesh mesh = LoadMeshFromText(c.mesh_obj(), "obj", fmt::format("colliders[{}].mesh_obj", i),
                                                     limits.collider_text);
          CheckMagnitude(mesh.vertices, "mesh_obj:");
          out.push_back(Collider::Mesh(mesh, limits.collider));
          break;
        }
        case v1::Collider::kMesh:
          out.push_back(Collider::Mesh(MeshFromArrays(c.mesh(), i, limits.collider), limits.collider));
          break;
        case v1::Collider::SHAPE_NOT_SET:
          Invalid("no shape set");
      }
    } catch (const Error& e) {
      // Prefixed once: a mesh's own messages already name it by its source (colliders[0].mesh_obj).
      const std::string at = fmt::format("colliders[{}]", i), what = e.what();
      Invalid(what.rfind(at, 0) == 0 ? what : at + ": " + what);
    }
  }
  return out;
}

Frame ToFrame(const v1::FrameRequest& in, const Rig& rig, size_t colliders, size_t f) {
  Frame frame;
  frame.weights.assign(in.weights().begin(), in.weights().end());
  // Exactly as large as FrameBytes counts.
  frame.pins.reserve(static_cast<size_t>(std::min(in.pins_size(), rig.num_surface_vertices())));
  frame.collider_transforms.reserve(static_cast<size_t>(std::min<int>(in.collider_transforms_size(), colliders)));
  if (in.collider_transforms_size() > static_cast<int>(colliders)) {
    Invalid(fmt::format("frames[{}]: collider_transforms has {} entries but there are {} colliders", f,
                        in.collider_transforms_size(), colliders));
  }
  for (int k = 0; k < in.collider_transforms_size(); ++k) {
    const v1::Transform& t = in.collider_transforms(k);
    CheckMagnitude(t.translation(), fmt::format("frames[{}].collider_transforms[{}].translation", f, k));
    RigidTransform motion;
    motion.translation = ToVector(t.translation());
    if (t.qw() != 0.0 || t.qx() != 0.0 || t.qy() != 0.0 || t.qz() != 0.0) {
      motion.rotation = Eigen::Quaterniond(t.qw(), t.qx(), t.qy(), t.qz());
      if (!(motion.rotation.norm() > 0.0) || !std::isfinite(motion.rotation.norm()) || !motion.rotation.coeffs().allFinite()) {
        Invalid(fmt::format("frames[{}].collider_transforms: not a finite quaternion", f));
      }
      motion.rotation.normalize();
    }
    frame.collider_transforms.push_back(motion);
  }
  if (in.pins_size() > rig.num_surface_vertices()) {
    Invalid(fmt::format("frames[{}].pins has {} entries, more than the mesh's {} vertices", f, in.pins_size(), rig.num_surface_vertices()));
  }
  for (int k = 0; k < in.pins_size(); ++k) {
    const v1::Pin& p = in.pins(k);
    CheckMagnitude(p.position(), fmt::format("frames[{}].pins[{}].position", f, k));
    if (p.vertex() >= static_cast<std::uint32_t>(rig.num_surface_vertices())) {
      Invalid(fmt::format("frames[{}].pins: vertex {} is not a vertex of the mesh (it has {})", f, p.vertex(), rig.num_surface_vertices()));
    }
    frame.pins.push_back({static_cast<int>(p.vertex()), ToVector(p.position())});
  }
  try {
    ValidateFrame(rig, frame, colliders);
  } catch (const Error& e) {
    Invalid(fmt::format("frames[{}]: {}", f, e.what()));
  }
  return frame;
}

void CheckSolved(const Points& positions, size_t index) {
  // Finite as float32, as the answer carries them (allFinite also catches NaN, which the max ignores).
  if (!positions.allFinite() ||
      (positions.size() > 0 && positions.cwiseAbs().maxCoeff() > std::numeric_limits<float>::max())) {
    throw Error(ErrorCode::kNumerical,
                fmt::format("frame {} produced positions that are not finite float32 values (weights, pins or "
                            "colliders too large); nothing was returned for it",
                            index));
  }
}

std::int64_t StreamBytes(const google::protobuf::RepeatedPtrField<v1::Collider>& colliders) {
  // A mesh collider holds its text's worth of vertices and faces several times over (our arrays, CGAL's
  // half-edge mesh, the AABB tree and its distance-query tree): about 16 bytes kept per byte of OBJ text, and
  // at most as much per byte of its arrays (a vertex is 24 bytes there, about as many as an OBJ line).
  std::int64_t bytes = 64 << 10;
  for (const auto& c : colliders) {
    bytes += 16 * static_cast<std::int64_t>(c.mesh_obj().size() + c.mesh().positions().size() +
                                            c.mesh().triangles().size());
  }
  return bytes;
}

namespace {

// A repeated message field holds a pointer per element and the element's own object (and its sub-messages).
constexpr std::int64_t kPointer = sizeof(void*);
constexpr std::int64_t kParsedPin = kPointer + sizeof(v1::Pin) + sizeof(v1::Vec3);
constexpr std::int64_t kParsedTransform = kPointer + sizeof(v1::Transform) + sizeof(v1::Vec3);

std::int64_t FrameBytes(size_t weights, size_t pins, size_t transforms) {
  return static_cast<std::int64_t>(sizeof(Frame) + weights * sizeof(double) + pins * sizeof(Pin) +
                                   transforms * sizeof(RigidTransform));
}

}  // namespace

std::int64_t RequestBytes(const v1::SolveRequest& request) {
  std::int64_t bytes = sizeof(v1::SolveRequest) + static_cast<std::int64_t>(request.character_id().size());
  for (const v1::Collider& c : request.colliders()) bytes += kPointer + static_cast<std::int64_t>(c.ByteSizeLong());
  for (const v1::FrameRequest& f : request.frames()) {
    bytes += kPointer + static_cast<std::int64_t>(sizeof(v1::FrameRequest)) +
             f.weights_size() * static_cast<std::int64_t>(sizeof(double)) + f.pins_size() * kParsedPin +
             f.collider_transforms_size() * kParsedTransform;
  }
  return bytes;
}

std::int64_t FrameBytes(const v1::FrameRequest& frame) {
  return FrameBytes(static_cast<size_t>(frame.weights_size()), static_cast<size_t>(frame.pins_size()),
                    static_cast<size_t>(frame.collider_transforms_size()));
}

std::int64_t FrameBytes(const Frame& frame) {
  return FrameBytes(frame.weights.capacity(), frame.pins.capacity(), frame.collider_transforms.capacity());
}

SolveJob ToSolveJob(const v1::SolveRequest& request, const Rig& rig, const Limits& limits,
                    const std::function<bool()>& stopped) {
  SolveJob job;
  if (request.frames_size() == 0) Invalid("frames is empty: send at least one frame");
  if (request.frames_size() > limits.max_frames) {
    throw LimitError(fmt::format("{} frames is over the limit of {} (--max-frames)", request.frames_size(), limits.max_frames));
  }
  ToOptions(request.options(), &job);
  try {
    ValidateOptions(rig, job.options);
  } catch (const Error& e) {
    Invalid(std::string("options: ") + e.what());
  }
  job.colliders = ToColliders(request.colliders(), limits, stopped);
  for (int f = 0; f < request.frames_size(); ++f) {
    if (f % 1024 == 0 && stopped && stopped()) throw CancelledError(fmt::format("stopped while reading frames[{}]", f));
    job.frames.push_back(ToFrame(request.frames(f), rig, job.colliders.size(), static_cast<size_t>(f)));
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
  s->set_finish(ToString(summary.finish));
  s->set_solved_vertices(summary.solved_vertices);
  s->set_free_vertices(summary.free_vertices);
  s->set_minimum(ToString(summary.minimum));
  s->set_certify_ms(summary.certify_ms);
  return out;
}

}  // namespace springblend::server
