#include "scene.h"

#include <fmt/format.h>

#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "springblend/error.h"

namespace springblend::cli {

// "VERTEX:x,y,z" -> a pin.
Pin ParsePin(const std::string& spec) {
  const auto colon = spec.find(':');
  Pin pin;
  try {
    if (colon == std::string::npos) throw std::invalid_argument("no colon");
    size_t used = 0;
    pin.vertex = std::stoi(spec.substr(0, colon), &used);
    if (used != colon) throw std::invalid_argument("vertex");
    std::stringstream in(spec.substr(colon + 1));
    std::string item;
    for (int c = 0; c < 3; ++c) {
      if (!std::getline(in, item, ',')) throw std::invalid_argument("too few");
      pin.position[c] = std::stod(item, &used);
      if (used != item.size()) throw std::invalid_argument(item);
    }
    if (std::getline(in, item, ',')) throw std::invalid_argument("too many");
  } catch (const std::exception&) {
    throw Error(ErrorCode::kInvalidInput, "--pin '" + spec + "': expected VERTEX:x,y,z");
  }
  return pin;
}

Scene LoadScene(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error(ErrorCode::kNotFound, "frames file not found: " + path);
  std::ostringstream text;
  text << in.rdbuf();
  return ParseScene(text.str(), path);
}

Scene ParseScene(const std::string& text, const std::string& path) {
  nlohmann::json doc;
  try {
    doc = nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    throw Error(ErrorCode::kInvalidInput, path + ": not valid JSON: " + e.what());
  }
  Scene scene;
  auto vec3 = [&](const nlohmann::json& j, const std::string& where) {
    if (!j.is_array() || j.size() != 3) throw Error(ErrorCode::kInvalidInput, path + ": " + where + " must be [x, y, z]");
    return Eigen::Vector3d(j[0].get<double>(), j[1].get<double>(), j[2].get<double>());
  };
  try {
    if (doc.contains("colliders")) scene.colliders = doc["colliders"].get<std::vector<std::string>>();
    if (!doc.contains("frames") || !doc["frames"].is_array() || doc["frames"].empty()) {
      throw Error(ErrorCode::kInvalidInput, path + ": needs a non-empty \"frames\" array");
    }
    for (size_t i = 0; i < doc["frames"].size(); ++i) {
      const auto& f = doc["frames"][i];
      const std::string where = fmt::format("frames[{}]", i);
      Frame frame;
      if (!f.contains("weights")) throw Error(ErrorCode::kInvalidInput, path + ": " + where + " has no \"weights\"");
      frame.weights = f["weights"].get<std::vector<double>>();
      if (f.contains("colliders")) {
        for (size_t c = 0; c < f["colliders"].size(); ++c) {
          const auto& m = f["colliders"][c];
          RigidTransform motion;
          const std::string cw = fmt::format("{}.colliders[{}]", where, c);
          if (m.contains("translation")) motion.translation = vec3(m["translation"], cw + ".translation");
          if (m.contains("rotation")) {
            const auto& q = m["rotation"];
            if (!q.is_array() || q.size() != 4) {
              throw Error(ErrorCode::kInvalidInput, path + ": " + cw + ".rotation must be a quaternion [w, x, y, z]");
            }
            motion.rotation = Eigen::Quaterniond(q[0].get<double>(), q[1].get<double>(), q[2].get<double>(),
                                                 q[3].get<double>());
            if (!(motion.rotation.norm() > 1e-12)) {
              throw Error(ErrorCode::kInvalidInput, path + ": " + cw + ".rotation is zero");
            }
            motion.rotation.normalize();
          }
          frame.collider_transforms.push_back(motion);
        }
      }
      if (f.contains("pins")) {
        for (size_t k = 0; k < f["pins"].size(); ++k) {
          const auto& p = f["pins"][k];
          frame.pins.push_back({p.at("vertex").get<int>(), vec3(p.at("position"), fmt::format("{}.pins[{}].position", where, k))});
        }
      }
      scene.frames.push_back(std::move(frame));
    }
  } catch (const nlohmann::json::exception& e) {
    throw Error(ErrorCode::kInvalidInput, path + ": " + e.what());
  }
  return scene;
}

}  // namespace springblend::cli
