// A DCC plug-in as studios build them: a MODULE library (a Maya or Houdini plug-in is a shared object the host
// dlopens) that links springblend::sdk alone. plugin_host loads it and calls springblend_plugin_run, which talks
// to a real server: upload a cylinder whose target moves every vertex with its outer rim held, solve frames by
// target name with a ball in the way, and get a refusal by status name.
#include <springblend/sdk.h>

#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>

namespace sdk = springblend::sdk;

namespace {

int failures = 0;

void Expect(bool ok, const std::string& what) {
  std::printf("%s%s\n", ok ? "plugin ok: " : "plugin FAILED: ", what.c_str());
  if (!ok) ++failures;
}

// 'v' and 'f' lines (what the host would hand over as arrays).
sdk::Mesh ReadObj(const std::string& path, const std::string& name) {
  std::ifstream file(path);
  if (!file) throw std::runtime_error("cannot open " + path);
  sdk::Mesh mesh;
  mesh.name = name;
  for (std::string line; std::getline(file, line);) {
    std::istringstream fields(line);
    std::string tag;
    fields >> tag;
    if (tag == "v") {
      double x = 0, y = 0, z = 0;
      fields >> x >> y >> z;
      mesh.positions.insert(mesh.positions.end(), {x, y, z});
    } else if (tag == "f") {
      for (int k = 0; k < 3; ++k) {
        std::string token;
        fields >> token;
        mesh.triangles.push_back(std::stoi(token.substr(0, token.find('/'))) - 1);
      }
    }
  }
  return mesh;
}

}  // namespace

extern "C" __attribute__((visibility("default"))) int springblend_plugin_run(const char* address, const char* dir,
                                                                              const char* version) {
  try {
    Expect(std::string(sdk::Version()) == version, std::string("the SDK is version ") + sdk::Version());
    sdk::Connection connection;
    connection.address = address;
    connection.timeout_seconds = 60;
    sdk::Client client(connection);
    Expect(client.Healthy(), "the server is healthy");

    const sdk::Mesh rest = ReadObj(std::string(dir) + "/cylinder.obj", "rest");
    sdk::Target twist;
    twist.mesh = ReadObj(std::string(dir) + "/poses-1_cylinder-2.obj", "twist");
    sdk::BuildOptions options;
    options.no_anchor = true;
    options.no_target_paths = true;
    options.hold_outer_rim = true;
    const sdk::Character character = client.Upload(rest, {twist}, options, "plugin-cylinder");
    Expect(character.id.size() == 64, "uploaded as " + character.id);
    Expect(character.boundary_mode == "fixed_vertices", "held by its rim: " + character.boundary_mode);
    Expect(character.target_names.size() == 1 && character.target_names[0] == "twist", "its target is 'twist'");

    std::vector<sdk::Frame> frames(2);
    frames[0].named_weights = {{"twist", 0.5}};
    frames[1].named_weights = {{"twist", 1.0}};
    int converged = 0;
    size_t values = 0;
    const int received = client.Solve(character.id, frames, {sdk::Collider::Sphere({0.0, 0.75, 0.75}, 0.3)}, {},
                                      [&](const sdk::SolvedFrame& frame) {
                                        converged += frame.converged ? 1 : 0;
                                        values = frame.positions.size();
                                      });
    Expect(received == 2 && converged == 2, std::to_string(converged) + " of 2 frames converged");
    Expect(values == rest.positions.size(), std::to_string(values / 3) + " vertices a frame");

    frames[1].named_weights = {{"jawOpen", 1.0}};
    try {
      client.Solve(character.id, frames, {}, {}, {});
      Expect(false, "an unknown weight name is refused");
    } catch (const sdk::Error& e) {
      Expect(e.status() == "INVALID_ARGUMENT" && std::string(e.what()).find("'jawOpen'") != std::string::npos,
             std::string("an unknown weight name is refused: ") + e.what());
    }
    try {
      client.Get(std::string(64, '0'));
      Expect(false, "an unknown character is NOT_FOUND");
    } catch (const sdk::Error& e) {
      Expect(e.status() == "NOT_FOUND", std::string("an unknown character: ") + e.what());
    }
    client.Delete(character.id);
  } catch (const std::exception& e) {
    Expect(false, std::string("unexpected exception: ") + e.what());
  }
  return failures;
}
