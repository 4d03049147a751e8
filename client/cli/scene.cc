#include "scene.h"

#include <fmt/format.h>

#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include <iostream>

#include "springblend/client.h"
#include "springblend/error.h"
#include "take.h"

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

Weights ParseWeightItems(const std::vector<std::string>& items) {
  Weights out;
  for (size_t i = 0; i < items.size(); ++i) {
    const std::string& item = items[i];
    const auto equals = item.find('=');
    const bool named = equals != std::string::npos;
    if (i > 0 && named != out.by_name) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("--weights: '{}': give every weight by name (NAME=W,...) or none (W,W,...)", item));
    }
    out.by_name = named;
    const std::string number = named ? item.substr(equals + 1) : item;
    double value = 0.0;
    try {
      size_t used = 0;
      value = std::stod(number, &used);
      if (used != number.size()) throw std::invalid_argument(number);
    } catch (const std::exception&) {
      throw Error(ErrorCode::kInvalidInput,
                  fmt::format("--weights: '{}' is not {}", item, named ? "NAME=NUMBER" : "a number"));
    }
    if (named) {
      const std::string name = item.substr(0, equals);
      if (name.empty()) throw Error(ErrorCode::kInvalidInput, fmt::format("--weights: '{}' has no target name", item));
      out.named.emplace_back(name, value);
    } else {
      out.values.push_back(value);
    }
  }
  return out;
}

std::vector<double> ResolveWeights(const Weights& weights, const std::vector<std::string>& names,
                                   const std::string& where) {
  if (!weights.by_name) return weights.values;
  std::vector<double> out;
  if (const auto wrong = WeightsByName(weights.named, names, &out)) {
    throw Error(ErrorCode::kInvalidInput, fmt::format("{}: {}", where, *wrong));
  }
  return out;
}

void Scene::ResolveNames(const std::vector<std::string>& names) {
  for (size_t i = 0; i < frames.size() && i < written_weights.size(); ++i) {
    if (written_weights[i].by_name) {
      frames[i].weights = ResolveWeights(written_weights[i], names, fmt::format("{}: frames[{}].weights", source, i));
    }
  }
}

std::string Scene::FrameName(size_t i) const {
  if (i < lines.size()) return fmt::format("{} line {}", source, lines[i]);
  return fmt::format("frames[{}]", i);
}

void AddFramesOptions(CLI::App* command, FramesInput* input) {
  command->add_option("--frames", input->frames_file,
                      "a JSON scene (weights, collider motions and pins per frame; see README), or a captured take "
                      "(a Live Link Face CSV, recognised by its header; docs/takes.md)");
  command->add_option("--take", input->take_file,
                      "a captured take (Live Link Face CSV: ARKit's shapes per frame) driving the targets by name; "
                      "a .pc2 output starts at the take's timecode")
      ->excludes(command->get_option("--frames"));
  command->add_option("--map", input->map_file,
                      "with a take: a JSON map of shape names to targets ({\"BrowInnerUp\": {\"brows_up\": 0.8}, "
                      "\"TongueOut\": null, ...}) for names the automatic matching misses");
  command->add_option("--lost", input->lost,
                      "with a take: rows where tracking was lost are held at the last tracked weights (hold: the "
                      "take's frame count and timing) or skipped (skip)")
      ->check(CLI::IsMember({"hold", "skip"}))
      ->capture_default_str();
}

void FramesInput::CheckTakeOptionsUnused() const {
  if (!map_file.empty() || lost != "hold") {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("--map and --lost go with a take (--take FILE, or --frames FILE with a take's header){}",
                            frames_file.empty() ? "" : "; " + frames_file + " is a JSON scene file"));
  }
}

Scene LoadFrames(const FramesInput& input, const std::vector<std::string>& names, CacheTiming* timing) {
  const bool is_take = !input.take_file.empty() || LooksLikeTake(input.frames_file);
  if (!is_take) {
    input.CheckTakeOptionsUnused();
    Scene scene = LoadScene(input.frames_file);
    scene.ResolveNames(names);
    return scene;
  }
  const std::string path = input.take_file.empty() ? input.frames_file : input.take_file;
  const Take take = ReadTake(path);
  ShapeMap map;
  if (!input.map_file.empty()) map = LoadShapeMap(input.map_file);
  const TakeFrames matched = MatchTake(take, names, input.map_file.empty() ? nullptr : &map,
                                       LostRowsFromString(input.lost));
  for (const std::string& line : matched.report.Lines()) std::cerr << "springblend: take " << path << ": " << line << "\n";
  Scene scene;
  scene.source = path;
  scene.lines = matched.lines;
  for (const auto& w : matched.weights) {
    scene.frames.push_back(Frame{w});
    scene.written_weights.push_back(Weights{w});
  }
  if (timing != nullptr && !timing->given && take.timing.known) {
    timing->start_frame = take.timing.start_frame;
    timing->sample_rate = 1.0;
  }
  return scene;
}

Scene ParseScene(const std::string& text, const std::string& path) {
  nlohmann::json doc;
  try {
    doc = nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    throw Error(ErrorCode::kInvalidInput, path + ": not valid JSON: " + e.what());
  }
  const auto invalid = [&](const std::string& where, const std::string& what) {
    return Error(ErrorCode::kInvalidInput, fmt::format("{}: {} {}", path, where, what));
  };
  const auto number = [&](const nlohmann::json& j, const std::string& where) {
    if (!j.is_number()) throw invalid(where, fmt::format("must be a number, not {}", j.type_name()));
    return j.get<double>();
  };
  const auto vec3 = [&](const nlohmann::json& j, const std::string& where) {
    if (!j.is_array() || j.size() != 3) throw invalid(where, "must be [x, y, z]");
    return Eigen::Vector3d(number(j[0], where + "[0]"), number(j[1], where + "[1]"), number(j[2], where + "[2]"));
  };
  const auto array = [&](const nlohmann::json& parent, const char* key,
                         const std::string& where) -> const nlohmann::json& {
    const nlohmann::json& j = parent[key];
    if (!j.is_array()) throw invalid(where, fmt::format("must be a list, not {}", j.type_name()));
    return j;
  };
  if (!doc.is_object()) throw invalid("the document", "must be an object with a \"frames\" list");
  Scene scene;
  scene.source = path;
  if (doc.contains("colliders")) {
    const nlohmann::json& colliders = array(doc, "colliders", "colliders");
    for (size_t c = 0; c < colliders.size(); ++c) {
      if (!colliders[c].is_string()) throw invalid(fmt::format("colliders[{}]", c), "must be a string such as \"sphere:0,0,0,1\"");
      scene.colliders.push_back(colliders[c].get<std::string>());
    }
  }
  if (!doc.contains("frames") || !doc["frames"].is_array() || doc["frames"].empty()) {
    throw Error(ErrorCode::kInvalidInput, path + ": needs a non-empty \"frames\" array");
  }
  const nlohmann::json& frames = doc["frames"];
  for (size_t i = 0; i < frames.size(); ++i) {
    const auto& f = frames[i];
    const std::string where = fmt::format("frames[{}]", i);
    if (!f.is_object()) throw invalid(where, "must be an object with \"weights\"");
    Frame frame;
    Weights written;
    if (!f.contains("weights")) throw Error(ErrorCode::kInvalidInput, path + ": " + where + " has no \"weights\"");
    const nlohmann::json& w = f["weights"];
    if (w.is_array()) {
      for (size_t k = 0; k < w.size(); ++k) written.values.push_back(number(w[k], fmt::format("{}.weights[{}]", where, k)));
      frame.weights = written.values;
    } else if (w.is_object()) {
      written.by_name = true;
      for (const auto& [name, value] : w.items()) {
        written.named.emplace_back(name, number(value, fmt::format("{}.weights.{}", where, name)));
      }
    } else {
      throw invalid(where + ".weights",
                    fmt::format("must be a list (one weight per target) or an object of target names to weights, "
                                "not {}",
                                w.type_name()));
    }
    if (f.contains("colliders")) {
      const nlohmann::json& colliders = array(f, "colliders", where + ".colliders");
      for (size_t c = 0; c < colliders.size(); ++c) {
        const auto& m = colliders[c];
        const std::string cw = fmt::format("{}.colliders[{}]", where, c);
        if (!m.is_object()) throw invalid(cw, "must be an object with \"translation\" and/or \"rotation\"");
        RigidTransform motion;
        if (m.contains("translation")) motion.translation = vec3(m["translation"], cw + ".translation");
        if (m.contains("rotation")) {
          const auto& q = m["rotation"];
          if (!q.is_array() || q.size() != 4) throw invalid(cw + ".rotation", "must be a quaternion [w, x, y, z]");
          const std::string qw = cw + ".rotation";
          motion.rotation = Eigen::Quaterniond(number(q[0], qw + "[0]"), number(q[1], qw + "[1]"),
                                               number(q[2], qw + "[2]"), number(q[3], qw + "[3]"));
          if (!(motion.rotation.norm() > 1e-12)) throw invalid(cw + ".rotation", "is zero");
          motion.rotation.normalize();
        }
        frame.collider_transforms.push_back(motion);
      }
    }
    if (f.contains("pins")) {
      const nlohmann::json& pins = array(f, "pins", where + ".pins");
      for (size_t k = 0; k < pins.size(); ++k) {
        const auto& p = pins[k];
        const std::string pw = fmt::format("{}.pins[{}]", where, k);
        if (!p.is_object() || !p.contains("vertex") || !p.contains("position")) {
          throw invalid(pw, "must be {\"vertex\": i, \"position\": [x, y, z]}");
        }
        if (!p["vertex"].is_number_integer()) throw invalid(pw + ".vertex", "must be a vertex index");
        frame.pins.push_back({p["vertex"].get<int>(), vec3(p["position"], pw + ".position")});
      }
    }
    scene.frames.push_back(std::move(frame));
    scene.written_weights.push_back(std::move(written));
  }
  return scene;
}

}  // namespace springblend::cli
