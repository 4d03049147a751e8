// Writes seed inputs for the upload and request fuzzers: well-formed uploads (a tetrahedron and a test mesh)
// in the upload fuzzer's framing, and solve requests using every collider kind, pins and options.
// and cache file payloads.
//   make_fuzz_seeds UPLOAD_DIR REQUEST_DIR CACHE_DIR MESH.obj
#include <fstream>
#include <iostream>
#include <string>

#include "character_store.h"
#include "springblend/mesh.h"
#include "springblend/v1/springblend.pb.h"

namespace {

using namespace springblend;

// One chunk as the upload fuzzer reads it: a 16-bit little-endian length, then the serialized chunk.
void Put(std::ofstream& out, const v1::UploadChunk& chunk) {
  const std::string bytes = chunk.SerializeAsString();
  if (bytes.size() > 0xffff) throw std::runtime_error("a seed chunk over 64 KiB");
  out.put(static_cast<char>(bytes.size() & 0xff)).put(static_cast<char>(bytes.size() >> 8)) << bytes;
}

void WriteUpload(const std::string& path, const TriangleMesh& rest) {
  std::ofstream out(path, std::ios::binary);
  v1::UploadChunk header;
  header.mutable_header()->set_name("seed");
  header.mutable_header()->set_vertex_count(static_cast<std::uint32_t>(rest.vertices.rows()));
  header.mutable_header()->set_face_count(static_cast<std::uint32_t>(rest.faces.rows()));
  header.mutable_header()->add_target_names("open");
  Put(out, header);
  const size_t per_piece = 1000;
  auto pieces = [&](v1::MeshPiece::Kind kind, std::uint32_t shape, const char* data, size_t count, size_t size) {
    for (size_t first = 0; first < count; first += per_piece) {
      v1::UploadChunk chunk;
      chunk.mutable_piece()->set_kind(kind);
      chunk.mutable_piece()->set_shape(shape);
      chunk.mutable_piece()->set_offset(static_cast<std::uint32_t>(first));
      chunk.mutable_piece()->set_data(data + first * size, std::min(per_piece, count - first) * size);
      Put(out, chunk);
    }
  };
  pieces(v1::MeshPiece::FACES, 0, reinterpret_cast<const char*>(rest.faces.data()), rest.faces.rows(), 12);
  Points target = rest.vertices;
  target.col(1) *= 1.2;
  pieces(v1::MeshPiece::POSITIONS, 0, reinterpret_cast<const char*>(rest.vertices.data()), rest.vertices.rows(), 24);
  pieces(v1::MeshPiece::POSITIONS, 1, reinterpret_cast<const char*>(target.data()), rest.vertices.rows(), 24);
}

v1::Vec3 Vec(double x, double y, double z) {
  v1::Vec3 v;
  v.set_x(x), v.set_y(y), v.set_z(z);
  return v;
}

void WriteRequests(const std::string& dir, const std::string& tet_obj) {
  v1::SolveRequest plain;
  plain.set_character_id(std::string(64, 'a'));
  for (double w : {0.0, 0.5, 1.0}) {
    v1::FrameRequest* f = plain.add_frames();
    f->add_weights(w), f->add_weights(1 - w);
  }
  std::ofstream(dir + "/plain.pb", std::ios::binary) << plain.SerializeAsString();

  v1::SolveRequest full = plain;
  v1::Collider* c = full.add_colliders();
  *c->mutable_sphere()->mutable_center() = Vec(0, 0, 2);
  c->mutable_sphere()->set_radius(0.5);
  c = full.add_colliders();
  *c->mutable_capsule()->mutable_a() = Vec(0, 0, 2);
  *c->mutable_capsule()->mutable_b() = Vec(1, 0, 2);
  c->mutable_capsule()->set_radius(0.2);
  c = full.add_colliders();
  *c->mutable_box()->mutable_center() = Vec(0, 3, 0);
  *c->mutable_box()->mutable_half_extents() = Vec(1, 1, 1);
  c = full.add_colliders();
  *c->mutable_plane()->mutable_point() = Vec(0, -1, 0);
  *c->mutable_plane()->mutable_normal() = Vec(0, 1, 0);
  full.add_colliders()->set_mesh_obj(tet_obj);
  // The same tetrahedron as arrays (Collider.mesh): float64 positions, int32 triangles.
  const TriangleMesh tet = LoadMeshFromText(tet_obj, "obj", "tetrahedron");
  v1::MeshArrays* arrays = full.add_colliders()->mutable_mesh();
  arrays->set_positions(reinterpret_cast<const char*>(tet.vertices.data()), sizeof(double) * tet.vertices.size());
  arrays->set_triangles(reinterpret_cast<const char*>(tet.faces.data()), sizeof(int) * tet.faces.size());
  for (auto& f : *full.mutable_frames()) {
    for (int k = 0; k < full.colliders_size(); ++k) {
      v1::Transform* t = f.add_collider_transforms();
      *t->mutable_translation() = Vec(0.1 * k, 0, 0);
      t->set_qw(1);
    }
    v1::Pin* pin = f.add_pins();
    pin->set_vertex(3);
    *pin->mutable_position() = Vec(0, 0, 1.2);
  }
  full.mutable_options()->set_residual_tolerance(1e-8);
  full.mutable_options()->set_max_iterations(50);
  full.mutable_options()->set_with_normals(true);
  std::ofstream(dir + "/full.pb", std::ios::binary) << full.SerializeAsString();
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 5) {
    std::cerr << "usage: make_fuzz_seeds UPLOAD_DIR REQUEST_DIR CACHE_DIR MESH.obj\n";
    return 2;
  }
  const std::string tet = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 3 1 4\n";
  WriteUpload(std::string(argv[1]) + "/tetrahedron", LoadMeshFromText(tet, "obj", "tetrahedron"));
  const TriangleMesh mesh = LoadMesh(argv[4]);
  WriteUpload(std::string(argv[1]) + "/mesh", mesh);
  WriteRequests(argv[2], tet);
  server::CharacterData character;
  character.name = "seed";
  character.target_names = {"open"};
  character.faces = mesh.faces;
  character.shapes = {mesh.vertices, mesh.vertices * 1.1};
  character.options.fixed_vertices = {0, 1};
  std::ofstream(std::string(argv[3]) + "/mesh", std::ios::binary) << server::Serialize(character);
  // A production rig: an in-between, a mask and a combination (the section after the shapes).
  character.target_names = {"open", "wide", "open_wide"};
  character.shapes = {mesh.vertices, mesh.vertices * 1.1, mesh.vertices * 0.9, mesh.vertices * 1.05};
  character.target_rigs.resize(3);
  character.target_rigs[0].inbetween_weights = {0.5};
  character.target_rigs[0].inbetweens = {mesh.vertices * 1.05};
  character.target_rigs[1].mask.assign(static_cast<size_t>(mesh.vertices.rows()), 0.5);
  character.target_rigs[2].combination = {"open", "wide"};
  std::ofstream(std::string(argv[3]) + "/rig", std::ios::binary) << server::Serialize(character);
  return 0;
}
