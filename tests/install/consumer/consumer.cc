// A plug-in's use of the installed client: health, upload a rig, list it, solve a frame, decode the positions.
//   consumer ADDRESS MESH_DIR VERSION      (MESH_DIR: tests/data/cylinder)
// Prints what it did; exits non-zero at the first thing that is not as expected.
#include <springblend/client.h>
#include <springblend/version.h>

#include <cstdlib>
#include <fstream>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

namespace {

int failures = 0;

void Expect(bool ok, const std::string& what) {
  std::cout << (ok ? "ok: " : "FAILED: ") << what << "\n";
  if (!ok) ++failures;
}

// 'v' and 'f' lines only; "f a/b/c" keeps the vertex index a (what a plug-in gets from its host, in short).
springblend::TriangleMesh ReadObj(const std::string& path, const std::string& name) {
  std::ifstream file(path);
  if (!file) throw std::runtime_error("cannot open " + path);
  std::vector<double> points;
  std::vector<int> corners;
  for (std::string line; std::getline(file, line);) {
    std::istringstream fields(line);
    std::string tag;
    fields >> tag;
    if (tag == "v") {
      double x = 0, y = 0, z = 0;
      fields >> x >> y >> z;
      points.insert(points.end(), {x, y, z});
    } else if (tag == "f") {
      for (int k = 0; k < 3; ++k) {
        std::string token;
        fields >> token;
        corners.push_back(std::stoi(token.substr(0, token.find('/'))) - 1);
      }
    }
  }
  springblend::TriangleMesh mesh;
  mesh.name = name;
  mesh.source = path;
  mesh.vertices = Eigen::Map<springblend::Points>(points.data(), static_cast<Eigen::Index>(points.size() / 3), 3);
  mesh.faces = Eigen::Map<springblend::Faces>(corners.data(), static_cast<Eigen::Index>(corners.size() / 3), 3);
  return mesh;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 4) {
    std::cerr << "usage: consumer ADDRESS MESH_DIR VERSION\n";
    return 2;
  }
  const std::string address = argv[1], dir = argv[2], version = argv[3];
  Expect(version == springblend::kVersion, "springblend/version.h says " + std::string(springblend::kVersion));
  try {
    springblend::ClientOptions options;
    options.address = address;
    options.timeout = std::chrono::seconds(60);
    springblend::Client client(options);
    Expect(client.Healthy(), "the server is healthy");

    const springblend::TriangleMesh rest = ReadObj(dir + "/cylinder.obj", "rest");
    const std::vector<springblend::TriangleMesh> targets = {ReadObj(dir + "/poses-1_cylinder-1.obj", "bend"),
                                                            ReadObj(dir + "/poses-1_cylinder-2.obj", "twist")};
    const springblend::v1::Character character = client.Upload(rest, targets, {}, "consumer-cylinder");
    Expect(!character.id().empty(), "uploaded " + character.name() + " as " + character.id());
    // The server found its TetGen helper (a rig without one has no tetrahedra).
    Expect(character.summary().tetrahedra() > 0,
           "the rig has " + std::to_string(character.summary().tetrahedra()) + " tetrahedra (" +
               character.summary().interior_reason() + ")");

    bool listed = false;
    for (const auto& c : client.List()) listed = listed || c.id() == character.id();
    Expect(listed, "List shows the character");

    springblend::v1::SolveRequest request;
    request.set_character_id(character.id());
    auto* frame = request.add_frames();
    frame->add_weights(0.5);
    frame->add_weights(0.0);
    int frames = 0;
    client.Solve(request, [&](const springblend::v1::SolvedFrame& solved) {
      const springblend::Points positions = springblend::Client::Decode(solved.positions());
      Expect(positions.rows() == rest.vertices.rows() && positions.allFinite(),
             "frame " + std::to_string(solved.index()) + ": " + std::to_string(positions.rows()) +
                 " finite positions, " + solved.summary().termination());
      ++frames;
    });
    Expect(frames == 1, "one frame solved");
  } catch (const springblend::ClientError& e) {
    Expect(false, std::string("client error ") + std::to_string(e.code()) + ": " + e.what());
  }
  return failures == 0 ? 0 : 1;
}
