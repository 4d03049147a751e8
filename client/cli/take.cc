#include "take.h"

#include <fmt/format.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <charconv>
#include <cmath>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <sstream>
#include <string_view>

#include "springblend/error.h"

namespace springblend::cli {
namespace {

// ARKit's 52 blendshapes, as Live Link Face writes them.
constexpr std::array<std::string_view, 52> kArkitShapes = {
    "EyeBlinkLeft",     "EyeLookDownLeft",   "EyeLookInLeft",     "EyeLookOutLeft",     "EyeLookUpLeft",
    "EyeSquintLeft",    "EyeWideLeft",       "EyeBlinkRight",     "EyeLookDownRight",   "EyeLookInRight",
    "EyeLookOutRight",  "EyeLookUpRight",    "EyeSquintRight",    "EyeWideRight",       "JawForward",
    "JawRight",         "JawLeft",           "JawOpen",           "MouthClose",         "MouthFunnel",
    "MouthPucker",      "MouthRight",        "MouthLeft",         "MouthSmileLeft",     "MouthSmileRight",
    "MouthFrownLeft",   "MouthFrownRight",   "MouthDimpleLeft",   "MouthDimpleRight",   "MouthStretchLeft",
    "MouthStretchRight", "MouthRollLower",   "MouthRollUpper",    "MouthShrugLower",    "MouthShrugUpper",
    "MouthPressLeft",   "MouthPressRight",   "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft",
    "MouthUpperUpRight", "BrowDownLeft",     "BrowDownRight",     "BrowInnerUp",        "BrowOuterUpLeft",
    "BrowOuterUpRight", "CheekPuff",         "CheekSquintLeft",   "CheekSquintRight",   "NoseSneerLeft",
    "NoseSneerRight",   "TongueOut"};

// Timecode frame rates in use, for a take too short to show where its timecode's frames wrap.
constexpr std::array<int, 10> kTimecodeRates = {24, 25, 30, 48, 50, 60, 72, 96, 100, 120};

std::string Lower(std::string_view s) {
  std::string out(s);
  std::transform(out.begin(), out.end(), out.begin(), [](unsigned char c) { return std::tolower(c); });
  return out;
}

std::string_view Trim(std::string_view s) {
  while (!s.empty() && std::isspace(static_cast<unsigned char>(s.front()))) s.remove_prefix(1);
  while (!s.empty() && std::isspace(static_cast<unsigned char>(s.back()))) s.remove_suffix(1);
  return s;
}

std::vector<std::string_view> SplitFields(std::string_view line) {
  std::vector<std::string_view> fields;
  size_t start = 0;
  while (true) {
    const size_t comma = line.find(',', start);
    fields.push_back(Trim(line.substr(start, comma == std::string_view::npos ? std::string_view::npos : comma - start)));
    if (comma == std::string_view::npos) return fields;
    start = comma + 1;
  }
}

bool IsDigit(char c) { return c >= '0' && c <= '9'; }

// A decimal number: [+-]digits[.digits][(e|E)[+-]digits], digits on at least one side of the point. Python's
// springblend.performance accepts exactly these (float() alone would take "nan", "inf" and "1_0").
std::optional<double> ParseNumber(std::string_view s) {
  size_t i = 0;
  if (i < s.size() && (s[i] == '+' || s[i] == '-')) ++i;
  const size_t integer = i;
  while (i < s.size() && IsDigit(s[i])) ++i;
  bool digits = i > integer;
  if (i < s.size() && s[i] == '.') {
    const size_t fraction = ++i;
    while (i < s.size() && IsDigit(s[i])) ++i;
    digits = digits || i > fraction;
  }
  if (!digits) return std::nullopt;
  if (i < s.size() && (s[i] == 'e' || s[i] == 'E')) {
    ++i;
    if (i < s.size() && (s[i] == '+' || s[i] == '-')) ++i;
    const size_t exponent = i;
    while (i < s.size() && IsDigit(s[i])) ++i;
    if (i == exponent) return std::nullopt;
  }
  if (i != s.size()) return std::nullopt;
  std::string_view text = s.front() == '+' ? s.substr(1) : s;
  double value = 0.0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  if (ec != std::errc() || end != text.data() + text.size() || !std::isfinite(value)) return std::nullopt;
  return value;
}

// HH:MM:SS:FF[.sss] (';' or '.' before FF too): seconds of the day and the frame.
struct Timecode {
  long seconds = 0;
  int frame = 0;
};

std::optional<Timecode> ParseTimecode(std::string_view s) {
  std::array<long, 4> parts{};
  size_t i = 0;
  for (int p = 0; p < 4; ++p) {
    const size_t start = i;
    while (i < s.size() && IsDigit(s[i]) && i - start < 6) ++i;
    if (i == start) return std::nullopt;
    std::from_chars(s.data() + start, s.data() + i, parts[p]);
    if (p < 3) {
      const char separator = i < s.size() ? s[i] : '\0';
      if (!(separator == ':' || (p == 2 && (separator == ';' || separator == '.')))) return std::nullopt;
      ++i;
    }
  }
  if (i < s.size()) {  // subframes
    if (s[i] != '.' || i + 1 == s.size()) return std::nullopt;
    for (++i; i < s.size(); ++i) {
      if (!IsDigit(s[i])) return std::nullopt;
    }
  }
  if (parts[1] > 59 || parts[2] > 59) return std::nullopt;
  return Timecode{parts[0] * 3600 + parts[1] * 60 + parts[2], static_cast<int>(parts[3])};
}

bool IsRotation(const std::string& lower) {
  const bool angle = lower.ends_with("yaw") || lower.ends_with("pitch") || lower.ends_with("roll");
  return angle && (lower.starts_with("head") || lower.find("eye") != std::string::npos);
}

bool IsArkitShape(const std::string& lower) {
  return std::any_of(kArkitShapes.begin(), kArkitShapes.end(), [&](std::string_view s) { return Lower(s) == lower; });
}

// The most frequent value (the smallest of equally frequent ones); nullopt for none.
std::optional<int> Mode(const std::vector<int>& values) {
  std::map<int, int> counts;
  for (int v : values) ++counts[v];
  std::optional<int> best;
  int best_count = 0;
  for (const auto& [v, n] : counts) {
    if (n > best_count) best = v, best_count = n;
  }
  return best;
}

TakeTiming InferTiming(const std::vector<Timecode>& codes) {
  TakeTiming timing;
  if (codes.size() < 2) return timing;
  std::vector<int> steps;
  int max_frame = 0;
  for (size_t i = 0; i < codes.size(); ++i) {
    max_frame = std::max(max_frame, codes[i].frame);
    if (i > 0 && codes[i].seconds == codes[i - 1].seconds && codes[i].frame > codes[i - 1].frame) {
      steps.push_back(codes[i].frame - codes[i - 1].frame);
    }
  }
  const std::optional<int> step = Mode(steps);
  if (!step) return timing;
  // Where the frames wrap into the next second: the frame that would have followed is the rate.
  std::vector<int> wraps;
  for (size_t i = 1; i < codes.size(); ++i) {
    if (((codes[i].seconds - codes[i - 1].seconds) % 86400 + 86400) % 86400 == 1) {
      wraps.push_back(codes[i - 1].frame + *step - codes[i].frame);
    }
  }
  const std::optional<int> wrapped = Mode(wraps);
  int rate = wrapped.value_or(0);
  if (rate <= max_frame) {
    const auto usual = std::find_if(kTimecodeRates.begin(), kTimecodeRates.end(), [&](int r) { return r > max_frame; });
    rate = usual == kTimecodeRates.end() ? max_frame + 1 : *usual;
    timing.rate_assumed = wraps.empty();
  }
  timing.known = true;
  timing.timecode_rate = rate;
  timing.step = *step;
  timing.frame_rate = static_cast<double>(rate) / *step;
  timing.start_frame =
      (static_cast<double>(codes.front().seconds) * rate + codes.front().frame) / static_cast<double>(*step);
  return timing;
}

// A name as (base, side): lower case without '_', '.', '-' or spaces, and "l", "r" or "" for a side suffix
// (Left/Right, _L/_R, .L/.R, -L/-R, or L/R right after a lower-case letter or digit).
std::pair<std::string, std::string> SideKey(const std::string& name) {
  std::string rest = name;
  std::string side;
  const std::string lower = Lower(name);
  const auto is_separator = [](char c) { return c == '_' || c == '.' || c == '-' || c == ' '; };
  if (lower.size() > 4 && lower.ends_with("left")) {
    side = "l", rest = name.substr(0, name.size() - 4);
  } else if (lower.size() > 5 && lower.ends_with("right")) {
    side = "r", rest = name.substr(0, name.size() - 5);
  } else if (lower.size() >= 3 && is_separator(name[name.size() - 2]) && (lower.back() == 'l' || lower.back() == 'r')) {
    side = std::string(1, lower.back()), rest = name.substr(0, name.size() - 2);
  } else if (name.size() >= 2 && (name.back() == 'L' || name.back() == 'R') &&
             (std::islower(static_cast<unsigned char>(name[name.size() - 2])) || IsDigit(name[name.size() - 2]))) {
    side = std::string(1, lower.back()), rest = name.substr(0, name.size() - 1);
  }
  std::string base;
  for (char c : rest) {
    if (!is_separator(c)) base += static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  }
  return {base, side};
}

std::string Joined(const std::vector<std::string>& names) { return fmt::format("{}", fmt::join(names, ", ")); }

// "1 row", "8 rows".
std::string Count(int n, const std::string& noun) { return fmt::format("{} {}{}", n, noun, n == 1 ? "" : "s"); }

// A file's bytes; Error(kNotFound) with `missing` and the path when it cannot be opened.
std::string ReadFile(const std::string& path, const std::string& missing) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(ErrorCode::kNotFound, missing + path);
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace

int Take::lost_rows() const {
  return static_cast<int>(std::count_if(rows.begin(), rows.end(), [](const TakeRow& r) { return !r.tracked; }));
}

bool LooksLikeTake(const std::string& path) {
  std::ifstream in(path);
  std::string line;
  if (!in || !std::getline(in, line)) return false;
  if (line.starts_with("\xEF\xBB\xBF")) line.erase(0, 3);
  for (std::string_view field : SplitFields(line)) {
    const std::string lower = Lower(field);
    if (lower == "timecode" || lower == "blendshapecount" || IsArkitShape(lower)) return true;
  }
  return false;
}

Take ReadTake(const std::string& path) { return ParseTake(ReadFile(path, "take file not found: "), path); }

Take ParseTake(const std::string& text, const std::string& source) {
  Take take;
  take.source = source;
  std::string_view rest(text);
  if (rest.starts_with("\xEF\xBB\xBF")) rest.remove_prefix(3);
  int line_number = 0;
  const auto next_line = [&](std::string_view* line) {
    if (rest.empty()) return false;
    const size_t end = rest.find('\n');
    *line = rest.substr(0, end);
    rest = end == std::string_view::npos ? std::string_view() : rest.substr(end + 1);
    if (line->ends_with('\r')) line->remove_suffix(1);
    ++line_number;
    return true;
  };
  const auto invalid = [&](int line, int column, const std::string& what) {
    return Error(ErrorCode::kInvalidInput, fmt::format("{}: line {}, column {}: {}", source, line, column, what));
  };
  std::string_view header_line;
  if (!next_line(&header_line) || Trim(header_line).empty()) {
    throw Error(ErrorCode::kInvalidInput, source + ": line 1: empty, not a take's header (Timecode,BlendShapeCount,"
                                                   "EyeBlinkLeft,...)");
  }
  const std::vector<std::string_view> header = SplitFields(header_line);
  int timecode_column = -1, count_column = -1;
  bool known = false;
  for (size_t c = 0; c < header.size(); ++c) {
    const std::string name(header[c]);
    const std::string lower = Lower(name);
    const int column = static_cast<int>(c);
    if (name.empty()) throw invalid(1, column + 1, "a column without a name");
    if (lower == "timecode") {
      timecode_column = column;
      known = true;
    } else if (lower == "blendshapecount") {
      count_column = column;
      known = true;
    } else if (IsRotation(lower)) {
      take.other_columns.push_back(name);
    } else {
      known = known || IsArkitShape(lower);
      take.shapes.push_back(name);
      take.shape_columns.push_back(column);
    }
  }
  if (!known) {
    throw invalid(1, 1, "not a take's header: no Timecode, BlendShapeCount or ARKit shape column (EyeBlinkLeft ... "
                        "JawOpen ... TongueOut)");
  }
  if (take.shapes.empty()) throw invalid(1, 1, "the header names no shape column (only timecode and rotations)");

  std::vector<Timecode> codes;
  std::string_view line;
  while (next_line(&line)) {
    if (Trim(line).empty()) continue;
    const std::vector<std::string_view> fields = SplitFields(line);
    TakeRow row;
    row.line = line_number;
    if (fields.size() > header.size()) {
      throw invalid(line_number, static_cast<int>(header.size()) + 1,
                    fmt::format("{} fields, but the header has {} columns", fields.size(), header.size()));
    }
    if (count_column >= 0 && static_cast<size_t>(count_column) < fields.size()) {
      const std::optional<double> count = ParseNumber(fields[count_column]);
      if (!count) {
        throw invalid(line_number, count_column + 1,
                      fmt::format("({}) '{}' is not a number", header[count_column], fields[count_column]));
      }
      row.tracked = *count != 0.0;
    }
    if (row.tracked && fields.size() < header.size()) {
      throw invalid(line_number, static_cast<int>(fields.size()) + 1,
                    fmt::format("the row ends after {} of the header's {} columns (a row where tracking was lost "
                                "has BlendShapeCount 0)",
                                fields.size(), header.size()));
    }
    if (timecode_column >= 0) {
      if (static_cast<size_t>(timecode_column) >= fields.size()) {
        throw invalid(line_number, timecode_column + 1, "the row has no timecode");
      }
      const std::optional<Timecode> code = ParseTimecode(fields[timecode_column]);
      if (!code) {
        throw invalid(line_number, timecode_column + 1,
                      fmt::format("({}) '{}' is not a timecode HH:MM:SS:FF[.sss]", header[timecode_column],
                                  fields[timecode_column]));
      }
      row.timecode = std::string(fields[timecode_column]);
      codes.push_back(*code);
    }
    if (row.tracked) {
      for (int c : take.shape_columns) {
        const std::optional<double> value = ParseNumber(fields[c]);
        if (!value) throw invalid(line_number, c + 1, fmt::format("({}) '{}' is not a number", header[c], fields[c]));
        row.values.push_back(*value);
      }
      // Rotations are left out, but a row whose rotation is not a number is no take's row.
      for (size_t c = 0; c < fields.size(); ++c) {
        if (static_cast<int>(c) != timecode_column && !ParseNumber(fields[c])) {
          throw invalid(line_number, static_cast<int>(c) + 1,
                        fmt::format("({}) '{}' is not a number", header[c], fields[c]));
        }
      }
    }
    take.rows.push_back(std::move(row));
  }
  if (take.rows.empty()) throw Error(ErrorCode::kInvalidInput, source + ": the take has a header but no rows");
  take.timing = InferTiming(codes);
  return take;
}

ShapeMap LoadShapeMap(const std::string& path) {
  return ParseShapeMap(ReadFile(path, "--map: map file not found: "), path);
}

ShapeMap ParseShapeMap(const std::string& text, const std::string& source) {
  nlohmann::ordered_json doc;  // the file's order: columns mapped twice add up in it
  try {
    doc = nlohmann::ordered_json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    throw Error(ErrorCode::kInvalidInput, source + ": not valid JSON: " + e.what());
  }
  const auto invalid = [&](const std::string& key, const std::string& what) {
    return Error(ErrorCode::kInvalidInput, fmt::format("{}: \"{}\": {}", source, key, what));
  };
  if (!doc.is_object()) {
    throw Error(ErrorCode::kInvalidInput,
                source + ": must be an object of shape names to a target, a list of targets, or {target: factor}");
  }
  ShapeMap map;
  map.source = source;
  for (const auto& [shape, value] : doc.items()) {
    std::vector<std::pair<std::string, double>> targets;
    if (value.is_string()) {
      targets.emplace_back(value.get<std::string>(), 1.0);
    } else if (value.is_array()) {
      for (const auto& t : value) {
        if (!t.is_string()) throw invalid(shape, "a list must hold target names");
        targets.emplace_back(t.get<std::string>(), 1.0);
      }
    } else if (value.is_object()) {
      for (const auto& [target, factor] : value.items()) {
        if (!factor.is_number() || !std::isfinite(factor.get<double>())) {
          throw invalid(shape, fmt::format("the factor of '{}' must be a number", target));
        }
        targets.emplace_back(target, factor.get<double>());
      }
    } else if (!value.is_null()) {
      throw invalid(shape, fmt::format("must be a target name, a list of them, {{target: factor}} or null, not {}",
                                       value.type_name()));
    }
    map.entries.emplace_back(shape, std::move(targets));
  }
  return map;
}

LostRows LostRowsFromString(const std::string& name) {
  if (name == "hold") return LostRows::kHold;
  if (name == "skip") return LostRows::kSkip;
  throw Error(ErrorCode::kInvalidInput, "--lost must be 'hold' or 'skip', got '" + name + "'");
}

std::vector<std::string> TakeReport::Lines() const {
  std::vector<std::string> lines;
  std::string when = "frame rate unknown (no Timecode column, or too few rows): a point cache starts at frame 1";
  if (timing.known) {
    when = fmt::format("{:g} frames per second (timecode at {} per second, step {}{}), first frame {:.15g}",
                       timing.frame_rate, timing.timecode_rate, timing.step,
                       timing.rate_assumed ? "; the take spans no second boundary, so the rate is assumed" : "",
                       timing.start_frame);
  }
  lines.push_back(fmt::format("{}, {}; {}", Count(rows, "row"), Count(frames, "frame"), when));
  if (!other_columns.empty()) lines.push_back("not weights, left out: " + Joined(other_columns));
  if (!unmatched_shapes.empty()) lines.push_back("shapes that drive no target: " + Joined(unmatched_shapes));
  if (!ambiguous_shapes.empty()) {
    lines.push_back("shapes that fit several targets, left out (name them in --map): " + Joined(ambiguous_shapes));
  }
  if (!unused_map_entries.empty()) lines.push_back("map entries for shapes the take lacks: " + Joined(unused_map_entries));
  if (!undriven_targets.empty()) {
    lines.push_back("targets no column drives (0 in every frame): " + Joined(undriven_targets));
  }
  if (!summed_targets.empty()) lines.push_back("targets several columns drive (their sum): " + Joined(summed_targets));
  if (!out_of_range.empty()) {
    std::vector<std::string> items;
    for (const auto& o : out_of_range) {
      items.push_back(fmt::format("{} in {} ({:g} to {:g}, first at line {})", o.target, Count(o.frames, "frame"),
                                  o.low, o.high, o.line));
    }
    lines.push_back("weights outside [0, 1]: " + Joined(items));
  }
  if (lost_rows > 0) {
    std::string line = fmt::format("tracking lost in {} (the longest stretch {}, from line {})", Count(lost_rows, "row"),
                                   Count(longest_lost, "row"), longest_lost_line);
    if (lost == LostRows::kSkip) {
      line += ", skipped";
      if (timing.known) line += ": the frames after the first lost row no longer keep the take's timing";
    } else {
      line += ", held at the last tracked weights";
      if (leading_lost_rows > 0) {
        line += fmt::format(" ({} before the first tracked one at its weights)", Count(leading_lost_rows, "row"));
      }
    }
    lines.push_back(line);
  }
  return lines;
}

TakeFrames MatchTake(const Take& take, const std::vector<std::string>& targets, const ShapeMap* map, LostRows lost) {
  TakeFrames out;
  TakeReport& report = out.report;
  report.source = take.source;
  report.rows = static_cast<int>(take.rows.size());
  report.timing = take.timing;
  report.other_columns = take.other_columns;
  report.lost = lost;

  // Each column's targets with factors.
  const size_t columns = take.shapes.size();
  std::vector<std::vector<std::pair<int, double>>> drives(columns);
  std::vector<bool> mapped(columns, false);
  const auto find_exact = [](const std::vector<std::string>& names, const std::string& name) -> std::vector<int> {
    std::vector<int> found;
    for (size_t i = 0; i < names.size(); ++i) {
      if (names[i] == name) return {static_cast<int>(i)};
    }
    for (size_t i = 0; i < names.size(); ++i) {
      if (Lower(names[i]) == Lower(name)) found.push_back(static_cast<int>(i));
    }
    return found;
  };
  if (map != nullptr) {
    for (const auto& [shape, entries] : map->entries) {
      const std::vector<int> column = find_exact(take.shapes, shape);
      if (column.empty()) {
        report.unused_map_entries.push_back(shape);
        continue;
      }
      for (int c : column) {
        mapped[c] = true;
        for (const auto& [target, factor] : entries) {
          const std::vector<int> t = find_exact(targets, target);
          if (t.size() != 1) {
            throw Error(ErrorCode::kInvalidInput,
                        fmt::format("{}: \"{}\": '{}' {} (targets: {})", map->source, shape, target,
                                    t.empty() ? "is not a target of the rig" : "names several targets (give its case)",
                                    Joined(targets)));
          }
          drives[c].emplace_back(t.front(), factor);
        }
      }
    }
  }
  std::vector<std::pair<std::string, std::string>> keys;
  for (const auto& t : targets) keys.push_back(SideKey(t));
  const auto with_key = [&](const std::pair<std::string, std::string>& key) {
    std::vector<int> found;
    for (size_t i = 0; i < keys.size(); ++i) {
      if (keys[i] == key) found.push_back(static_cast<int>(i));
    }
    return found;
  };
  for (size_t c = 0; c < columns; ++c) {
    if (mapped[c]) continue;
    const std::string& shape = take.shapes[c];
    std::vector<int> found = find_exact(targets, shape);
    const auto key = SideKey(shape);
    if (found.empty()) found = with_key(key);
    if (found.size() > 1) {
      std::vector<std::string> names;
      for (int t : found) names.push_back(targets[t]);
      report.ambiguous_shapes.push_back(fmt::format("{} ({})", shape, Joined(names)));
      continue;
    }
    if (found.empty() && key.second.empty()) {
      // A symmetric shape drives the halves of a target the rig splits into left and right.
      const std::vector<int> left = with_key({key.first, "l"}), right = with_key({key.first, "r"});
      if (left.size() > 1 || right.size() > 1) {
        std::vector<std::string> names;
        for (int t : left) names.push_back(targets[t]);
        for (int t : right) names.push_back(targets[t]);
        report.ambiguous_shapes.push_back(fmt::format("{} ({})", shape, Joined(names)));
        continue;
      }
      found = left;
      found.insert(found.end(), right.begin(), right.end());
    }
    if (found.empty()) {
      report.unmatched_shapes.push_back(shape);
      continue;
    }
    for (int t : found) drives[c].emplace_back(t, 1.0);
  }
  for (size_t c = 0; c < columns; ++c) {
    if (mapped[c] && drives[c].empty()) report.unmatched_shapes.push_back(take.shapes[c] + " (null in the map)");
  }
  std::vector<int> drivers(targets.size(), 0);
  for (const auto& d : drives) {
    for (const auto& [t, factor] : d) ++drivers[t];
  }
  bool any = false;
  for (size_t t = 0; t < targets.size(); ++t) {
    if (drivers[t] == 0) report.undriven_targets.push_back(targets[t]);
    if (drivers[t] > 1) report.summed_targets.push_back(targets[t]);
    any = any || drivers[t] > 0;
  }
  if (!any) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("{}: line 1: no column of the header is a shape of this rig (its targets: {}; the take's "
                            "shapes: {}); a --map names the others",
                            take.source, Joined(targets), Joined(take.shapes)));
  }

  // Rows into frames.
  const auto first_tracked =
      std::find_if(take.rows.begin(), take.rows.end(), [](const TakeRow& r) { return r.tracked; });
  if (first_tracked == take.rows.end()) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("{}: tracking was lost in every row (BlendShapeCount 0): nothing to solve", take.source));
  }
  const auto weights_of = [&](const TakeRow& row) {
    std::vector<double> w(targets.size(), 0.0);
    for (size_t c = 0; c < columns; ++c) {
      for (const auto& [t, factor] : drives[c]) w[t] += factor * row.values[c];
    }
    return w;
  };
  std::vector<double> held = weights_of(*first_tracked);
  int stretch = 0;
  for (const TakeRow& row : take.rows) {
    if (row.tracked) {
      held = weights_of(row);
      stretch = 0;
    } else {
      ++report.lost_rows;
      if (++stretch > report.longest_lost) report.longest_lost = stretch, report.longest_lost_line = row.line - stretch + 1;
      if (&row < &*first_tracked) ++report.leading_lost_rows;
      if (lost == LostRows::kSkip) continue;
    }
    out.weights.push_back(held);
    out.lines.push_back(row.line);
  }
  report.frames = static_cast<int>(out.weights.size());
  for (size_t t = 0; t < targets.size(); ++t) {
    TakeReport::OutOfRange o{targets[t]};
    for (size_t f = 0; f < out.weights.size(); ++f) {
      const double w = out.weights[f][t];
      if (w >= 0.0 && w <= 1.0) continue;
      if (o.frames++ == 0) o.low = o.high = w, o.line = out.lines[f];
      o.low = std::min(o.low, w), o.high = std::max(o.high, w);
    }
    if (o.frames > 0) report.out_of_range.push_back(o);
  }
  return out;
}

}  // namespace springblend::cli
