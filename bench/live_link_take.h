// A Live Link Face take (Epic's iOS app: ARKit's 52 shapes per frame) read into weights of a rig's targets, for the
// take benchmark and the mix tests. Minimal on purpose: rows where tracking was lost (fewer fields) are skipped and
// nothing is reported; the product's reader is the takes issue's.
#pragma once

#include <algorithm>
#include <cctype>
#include <fstream>
#include <map>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

namespace springblend::take {

struct Take {
  std::vector<std::string> shapes;         // the shape columns' names (Timecode, BlendShapeCount and rotations left out)
  std::vector<std::vector<double>> rows;   // one per tracked frame, one weight per shape
};

inline std::string Lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return std::tolower(c); });
  return s;
}

inline Take ReadTake(const std::string& file) {
  std::ifstream in(file);
  if (!in) throw std::runtime_error(file + ": cannot be read");
  std::string line;
  std::getline(in, line);
  std::vector<std::string> header;
  {
    std::stringstream ss(line);
    std::string field;
    while (std::getline(ss, field, ',')) header.push_back(field);
  }
  // The shapes run from the third column to the first head or eye rotation (HeadYaw, LeftEyePitch, ...).
  size_t end = header.size();
  for (size_t c = 2; c < header.size() && end == header.size(); ++c) {
    const std::string& h = header[c];
    const bool rotation = h.find("Yaw") != std::string::npos || h.find("Pitch") != std::string::npos ||
                          h.find("Roll") != std::string::npos;
    if (rotation && (h.rfind("Head", 0) == 0 || h.find("Eye") != std::string::npos)) end = c;
  }
  Take take;
  if (header.size() < 3) throw std::runtime_error(file + ": no shape columns");
  take.shapes.assign(header.begin() + 2, header.begin() + static_cast<std::ptrdiff_t>(end));
  while (std::getline(in, line)) {
    std::stringstream ss(line);
    std::string field;
    std::vector<double> values;
    size_t column = 0;
    while (std::getline(ss, field, ',')) {
      if (column >= 2 && column < end) values.push_back(std::stod(field));
      ++column;
    }
    if (values.size() == take.shapes.size()) take.rows.push_back(std::move(values));
  }
  return take;
}

// For each shape column, the targets it drives: its name case-insensitively, Left/Right as _L/_R, and a shape the
// rig splits into _L and _R driving both halves. Columns that match nothing drive nothing.
inline std::vector<std::vector<int>> MapShapes(const std::vector<std::string>& shapes,
                                               const std::vector<std::string>& targets) {
  std::map<std::string, int> index;
  for (size_t t = 0; t < targets.size(); ++t) index[Lower(targets[t])] = static_cast<int>(t);
  std::vector<std::vector<int>> map(shapes.size());
  for (size_t c = 0; c < shapes.size(); ++c) {
    const std::string name = Lower(shapes[c]);
    auto add = [&](const std::string& n) {
      const auto it = index.find(n);
      if (it != index.end()) map[c].push_back(it->second);
    };
    add(name);
    if (!map[c].empty()) continue;
    for (const auto& [side, suffix] : {std::pair<std::string, std::string>{"left", "_l"}, {"right", "_r"}}) {
      if (name.size() > side.size() && name.compare(name.size() - side.size(), side.size(), side) == 0) {
        add(name.substr(0, name.size() - side.size()) + suffix);
      }
    }
    if (map[c].empty()) {
      add(name + "_l");
      add(name + "_r");
    }
  }
  return map;
}

// The take's rows as weight vectors of the rig's targets.
inline std::vector<std::vector<double>> Weights(const Take& take, const std::vector<std::string>& targets) {
  const std::vector<std::vector<int>> map = MapShapes(take.shapes, targets);
  std::vector<std::vector<double>> frames;
  for (const auto& row : take.rows) {
    std::vector<double> w(targets.size(), 0.0);
    for (size_t c = 0; c < map.size(); ++c) {
      for (int t : map[c]) w[t] = row[c];
    }
    frames.push_back(std::move(w));
  }
  return frames;
}

}  // namespace springblend::take
