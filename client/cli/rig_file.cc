#include "rig_file.h"

#include <fmt/format.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>

#include "springblend/error.h"
#include "springblend/mesh.h"
#include "springblend/rig.h"

namespace springblend::cli {
namespace {

using nlohmann::json;

[[noreturn]] void Invalid(const std::string& what) { throw Error(ErrorCode::kInvalidInput, what); }

std::string ReadText(const std::filesystem::path& path, const std::string& where) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(ErrorCode::kNotFound, fmt::format("{}: cannot open {}", where, path.string()));
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

const char* TypeName(const json& j) { return j.type_name(); }

// Checks that `object` is an object with only `allowed` keys and the `required` ones.
void CheckKeys(const json& object, const std::string& where, const std::set<std::string>& allowed,
               const std::set<std::string>& required) {
  if (!object.is_object()) Invalid(fmt::format("{}: expected an object, got {}", where, TypeName(object)));
  for (const auto& [key, value] : object.items()) {
    if (allowed.count(key) == 0) {
      std::string names;
      for (const auto& a : allowed) names += (names.empty() ? "" : ", ") + a;
      Invalid(fmt::format("{}: unknown key '{}' (expected {})", where, key, names));
    }
  }
  for (const auto& key : required) {
    if (!object.contains(key)) Invalid(fmt::format("{}: '{}' is missing", where, key));
  }
}

std::string String(const json& j, const std::string& where) {
  if (!j.is_string()) Invalid(fmt::format("{}: expected a string, got {}", where, TypeName(j)));
  return j.get<std::string>();
}

double Number(const json& j, const std::string& where) {
  if (!j.is_number()) Invalid(fmt::format("{}: expected a number, got {}", where, TypeName(j)));
  const double value = j.get<double>();
  if (!std::isfinite(value)) Invalid(fmt::format("{}: {} is not finite", where, value));
  return value;
}

const json& Array(const json& j, const std::string& where) {
  if (!j.is_array()) Invalid(fmt::format("{}: expected a list, got {}", where, TypeName(j)));
  return j;
}

// A mesh named relative to the rig file, loaded in any format LoadMesh reads.
TriangleMesh Mesh(const json& j, const std::filesystem::path& base, const std::string& where) {
  const std::string relative = String(j, where);
  const std::filesystem::path path = base / relative;
  if (!std::filesystem::is_regular_file(path)) {
    throw Error(ErrorCode::kNotFound, fmt::format("{}: file not found: {}", where, path.string()));
  }
  try {
    return LoadMesh(path.string());
  } catch (const Error& e) {
    throw Error(e.code(), fmt::format("{}: {}", where, e.what()));
  }
}

std::vector<double> Mask(const json& j, const std::filesystem::path& base, const std::string& where, size_t vertices,
                         const std::string& rest) {
  std::vector<double> mask;
  std::string from = "";
  if (j.is_string()) {
    const std::filesystem::path path = base / j.get<std::string>();
    if (!std::filesystem::is_regular_file(path)) {
      throw Error(ErrorCode::kNotFound, fmt::format("{}: file not found: {}", where, path.string()));
    }
    mask = ParseMaskText(ReadText(path, where), fmt::format("{}: {}", where, path.string()));
    from = " in " + path.string();
  } else if (j.is_array()) {
    for (size_t v = 0; v < j.size(); ++v) mask.push_back(Number(j[v], fmt::format("{}[{}]", where, v)));
  } else {
    Invalid(fmt::format("{}: expected a list of weights (one per vertex) or the path of a text file, got {}", where,
                        TypeName(j)));
  }
  if (mask.size() != vertices) {
    Invalid(fmt::format("{}: {} values{}, but the rest mesh {} has {} vertices", where, mask.size(), from, rest, vertices));
  }
  return mask;
}

}  // namespace

std::vector<double> ParseMaskText(const std::string& text, const std::string& source) {
  std::vector<double> values;
  std::istringstream in(text);
  std::string line;
  for (int number = 1; std::getline(in, line); ++number) {
    const size_t first = line.find_first_not_of(" \t\r");
    if (first == std::string::npos || line[first] == '#') continue;
    const size_t last = line.find_last_not_of(" \t\r");
    const std::string item = line.substr(first, last - first + 1);
    double value = 0.0;
    const auto [end, error] = std::from_chars(item.data(), item.data() + item.size(), value);
    if (error != std::errc() || end != item.data() + item.size()) {
      Invalid(fmt::format("{}: line {}: '{}' is not a number (one weight per line)", source, number, item.substr(0, 40)));
    }
    if (!std::isfinite(value)) Invalid(fmt::format("{}: line {}: {} is not finite", source, number, item));
    values.push_back(value);
  }
  return values;
}

std::vector<std::string> RigFile::WeightNames() const {
  std::vector<std::string> names;
  for (const auto& t : targets) {
    if (t.combination.empty()) names.push_back(t.mesh.name);
  }
  return names;
}

RigFile LoadRigFile(const std::string& path) {
  RigFile rig;
  rig.path = path;
  const std::filesystem::path base = std::filesystem::path(path).parent_path();
  json doc;
  try {
    doc = json::parse(ReadText(path, "rig file"));
  } catch (const json::exception& e) {
    Invalid(fmt::format("{}: not valid JSON: {}", path, e.what()));
  }
  CheckKeys(doc, path, {"$schema", "rest", "fixed_vertices", "targets"}, {"rest", "targets"});  // $schema: for editors
  rig.rest = Mesh(doc["rest"], base, path + ": rest");
  const size_t vertices = static_cast<size_t>(rig.rest.vertices.rows());
  if (doc.contains("fixed_vertices")) {
    const json& fixed = Array(doc["fixed_vertices"], path + ": fixed_vertices");
    for (size_t i = 0; i < fixed.size(); ++i) {
      const std::string where = fmt::format("{}: fixed_vertices[{}]", path, i);
      if (!fixed[i].is_number_integer()) Invalid(fmt::format("{}: expected a vertex index, got {}", where, fixed[i].dump()));
      const auto v = fixed[i].get<std::int64_t>();
      if (v < 0 || static_cast<size_t>(v) >= vertices) {
        Invalid(fmt::format("{}: {} is not a vertex of the rest mesh (it has {})", where, v, vertices));
      }
      rig.fixed_vertices.push_back(static_cast<int>(v));
    }
  }
  const json& targets = Array(doc["targets"], path + ": targets");
  if (targets.empty()) Invalid(path + ": targets is empty: a rig needs at least one target");
  std::map<std::vector<std::string>, std::string> combinations;  // sorted drivers -> the first target with them
  for (size_t t = 0; t < targets.size(); ++t) {
    const json& in = targets[t];
    std::string where = fmt::format("{}: targets[{}]", path, t);
    CheckKeys(in, where, {"name", "mesh", "inbetweens", "mask", "combination"}, {"name", "mesh"});
    RigTarget target;
    const std::string name = String(in["name"], where + ".name");
    if (name.empty()) Invalid(where + ".name is empty");
    // Weights are given by name as NAME=WEIGHT,NAME=WEIGHT: a name with either character cannot be addressed.
    if (const size_t at = name.find_first_of("=,"); at != std::string::npos) {
      Invalid(fmt::format("{}.name '{}' contains '{}': weights given by name (NAME=WEIGHT,...) could not address it",
                          where, name, name[at]));
    }
    where = fmt::format("{}: target '{}'", path, name);
    target.mesh = Mesh(in["mesh"], base, where + ": mesh");
    target.mesh.name = name;
    if (in.contains("inbetweens")) {
      const json& list = Array(in["inbetweens"], where + ": inbetweens");
      for (size_t i = 0; i < list.size(); ++i) {
        const std::string at = fmt::format("{}: inbetweens[{}]", where, i);
        CheckKeys(list[i], at, {"weight", "mesh"}, {"weight", "mesh"});
        RigTarget::Inbetween inbetween;
        inbetween.weight = Number(list[i]["weight"], at + ".weight");
        inbetween.mesh = Mesh(list[i]["mesh"], base, at + ".mesh");
        inbetween.mesh.name = name;
        target.inbetweens.push_back(std::move(inbetween));
      }
    }
    if (in.contains("mask")) target.mask = Mask(in["mask"], base, where + ": mask", vertices, rig.rest.source);
    if (in.contains("combination")) {
      const json& list = Array(in["combination"], where + ": combination");
      for (size_t i = 0; i < list.size(); ++i) {
        target.combination.push_back(String(list[i], fmt::format("{}: combination[{}]", where, i)));
      }
      if (target.combination.empty()) Invalid(where + ": combination is empty (name at least two targets)");
      // a*b and b*a are one product of weights: two correctives on it would both switch on together.
      std::vector<std::string> drivers = target.combination;
      std::sort(drivers.begin(), drivers.end());
      const auto [first, added] = combinations.emplace(drivers, name);
      if (!added) {
        Invalid(fmt::format("{}: combination has the drivers of target '{}' (in any order, the same product of "
                            "weights): one combination per set of drivers",
                            where, first->second));
      }
    }
    rig.targets.push_back(std::move(target));
  }
  return rig;
}

std::shared_ptr<const Rig> BuildRig(RigFile file, RigOptions options) {
  options.fixed_vertices.insert(options.fixed_vertices.end(), file.fixed_vertices.begin(), file.fixed_vertices.end());
  std::vector<TargetSpec> specs;
  for (RigTarget& t : file.targets) {
    TargetSpec spec;
    spec.name = t.mesh.name;
    spec.mesh = std::move(t.mesh);
    for (auto& b : t.inbetweens) spec.inbetweens.push_back({b.weight, std::move(b.mesh)});
    spec.mask = std::move(t.mask);
    spec.combination = std::move(t.combination);
    specs.push_back(std::move(spec));
  }
  try {
    return Rig::Build(std::move(file.rest), std::move(specs), options);
  } catch (const Error& e) {
    throw Error(e.code(), fmt::format("{}: {}", file.path, e.what()));
  }
}

std::shared_ptr<const Rig> BuildRigFromFlags(const std::string& rig, const std::string& rest,
                                             const std::vector<std::string>& targets, const RigOptions& options,
                                             const std::string& otherwise) {
  if (!rig.empty()) {
    if (!rest.empty() || !targets.empty()) {
      throw Error(ErrorCode::kInvalidInput, "--rig names the rest shape and the targets; drop --rest and --target");
    }
    return BuildRig(LoadRigFile(rig), options);
  }
  if (rest.empty() || targets.empty()) {
    throw Error(ErrorCode::kInvalidInput, "give --rest and at least one --target, or --rig RIG.json" + otherwise);
  }
  std::vector<TriangleMesh> meshes;
  for (const auto& path : targets) meshes.push_back(LoadMesh(path));
  return Rig::Build(LoadMesh(rest), std::move(meshes), options);
}

}  // namespace springblend::cli
