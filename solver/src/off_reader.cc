#include "off_reader.h"

#include <fmt/format.h>

#include <cfloat>
#include <charconv>
#include <climits>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <optional>

#include "springblend/error.h"

namespace springblend {
namespace {

bool IsSpace(char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f'; }

// A word of the file as it may appear in a message: at most 32 bytes, anything unprintable escaped (a garbled
// or binary file must not put control bytes into logs).
std::string Quote(std::string_view word) {
  std::string out = "'";
  for (size_t i = 0; i < word.size() && i < 32; ++i) {
    const auto c = static_cast<unsigned char>(word[i]);
    out += c >= 0x20 && c < 0x7f ? std::string(1, static_cast<char>(c)) : fmt::format("\\x{:02x}", c);
  }
  if (word.size() > 32) out += "...";
  return out + "'";
}

// The file's lines that hold data (comments from '#' and blank lines skipped), one at a time, split into words.
class Lines {
 public:
  explicit Lines(std::string_view text) : text_(text) {
    if (text_.substr(0, 3) == "\xEF\xBB\xBF") text_.remove_prefix(3);  // a UTF-8 byte order mark
  }

  // Moves to the next line with data; false at the end of the file.
  bool Next() {
    words_.clear();
    while (at_ < text_.size()) {
      const size_t end = std::min(text_.find('\n', at_), text_.size());
      std::string_view line = text_.substr(at_, end - at_);
      at_ = end + 1;
      ++number_;
      line = line.substr(0, line.find('#'));
      for (size_t i = 0; i < line.size();) {
        while (i < line.size() && IsSpace(line[i])) ++i;
        const size_t start = i;
        while (i < line.size() && !IsSpace(line[i])) ++i;
        if (i > start) words_.push_back(line.substr(start, i - start));
      }
      if (!words_.empty()) return true;
    }
    return false;
  }

  // How many lines with data follow the current one (without moving).
  std::uint64_t CountRemaining() const {
    Lines rest = *this;
    std::uint64_t n = 0;
    while (rest.Next()) ++n;
    return n;
  }

  int number() const { return number_; }
  const std::vector<std::string_view>& words() const { return words_; }

 private:
  std::string_view text_;
  size_t at_ = 0;
  int number_ = 0;
  std::vector<std::string_view> words_;
};

// A count or an index: decimal digits only, at most INT_MAX.
std::optional<int> ParseInt(std::string_view word) {
  int value = 0;
  const auto [end, ec] = std::from_chars(word.data(), word.data() + word.size(), value);
  if (ec != std::errc() || end != word.data() + word.size() || value < 0 || word[0] == '-') return std::nullopt;
  return value;
}

// A number as OpenMesh reads it (a float32 through an istream): an optional sign, decimal digits, a point and an
// exponent. Overflow is refused; underflow gives zero or a denormal, as the stream does.
std::optional<float> ParseFloat(std::string_view word) {
  if (word.size() > 1 && word[0] == '+' && word[1] != '-' && word[1] != '+') word.remove_prefix(1);
  float value = 0.0f;
  const auto [end, ec] = std::from_chars(word.data(), word.data() + word.size(), value);
  if (end != word.data() + word.size() || word.empty()) return std::nullopt;
  if (ec == std::errc::result_out_of_range) {
    const double wide = std::strtod(std::string(word).c_str(), nullptr);
    if (!(std::abs(wide) <= FLT_MAX)) return std::nullopt;
    return static_cast<float>(wide);
  }
  if (ec != std::errc()) return std::nullopt;
  return value;
}

class OffReader {
 public:
  OffReader(std::string_view text, const std::string& source) : lines_(text), source_(source) {}

  PolygonSoup Read() {
    ReadKeyword();
    ReadCounts();
    PolygonSoup soup;
    soup.points.reserve(static_cast<size_t>(vertices_));
    for (int v = 0; v < vertices_; ++v) soup.points.push_back(ReadVertex(v));
    soup.polygons.reserve(static_cast<size_t>(faces_));
    for (int f = 0; f < faces_; ++f) soup.polygons.push_back(ReadFace(f));
    if (lines_.Next()) {
      Fail(fmt::format("data after the last face ({} faces and {} vertices, as the counts on line {} say): {}",
                       faces_, vertices_, counts_line_, Quote(lines_.words()[0])));
    }
    return soup;
  }

 private:
  [[noreturn]] void Fail(const std::string& what) const { FailAt(lines_.number(), what); }
  [[noreturn]] void FailAt(int line, const std::string& what) const {
    throw Error(ErrorCode::kInvalidInput, fmt::format("{}: line {}: {}", source_, line, what));
  }

  // [ST][C][N]OFF, optionally followed by the counts on the same line.
  void ReadKeyword() {
    if (!lines_.Next()) {
      throw Error(ErrorCode::kInvalidInput, fmt::format("{}: the file does not start with OFF: it is empty", source_));
    }
    std::string_view k = lines_.words()[0];
    const std::string_view keyword = k;
    const auto take = [&k](std::string_view prefix) {
      if (k.substr(0, prefix.size()) != prefix) return false;
      k.remove_prefix(prefix.size());
      return true;
    };
    texture_ = take("ST");
    color_ = take("C");
    normal_ = take("N");
    if (k == "4OFF" || k == "nOFF" || k == "4nOFF") {
      Fail(fmt::format("{}: only 3D vertices are supported (no 4OFF or nOFF)", Quote(keyword)));
    }
    if (k != "OFF") {
      Fail(fmt::format("the file does not start with OFF (or COFF, NOFF, CNOFF, STOFF, STCNOFF): found {}",
                       Quote(keyword)));
    }
    keyword_ = keyword;
    if (lines_.words().size() > 1 && lines_.words()[1] == "BINARY") {
      Fail("binary OFF is not supported; convert the file to ASCII OFF (or OBJ)");
    }
  }

  void ReadCounts() {
    // The counts follow the keyword on its line, or are the next line with data.
    std::vector<std::string_view> words(lines_.words().begin() + 1, lines_.words().end());
    if (words.empty()) {
      const int keyword_line = lines_.number();
      if (!lines_.Next()) FailAt(keyword_line, "the counts 'VERTICES FACES EDGES' are missing after the keyword");
      words = lines_.words();
    }
    counts_line_ = lines_.number();
    std::optional<int> v, f;
    if (words.size() >= 2) {
      v = ParseInt(words[0]);
      f = ParseInt(words[1]);
    }
    if (!v || !f || words.size() > 3 || (words.size() == 3 && !ParseInt(words[2]))) {
      Fail(fmt::format("expected the counts 'VERTICES FACES EDGES' (non-negative integers), found {}",
                       Quote(fmt::format("{}", fmt::join(words, " ")))));
    }
    vertices_ = *v;
    faces_ = *f;
    // One line per vertex and per face: refuse counts the rest of the file cannot hold before allocating.
    const std::uint64_t remaining = lines_.CountRemaining();
    if (static_cast<std::uint64_t>(vertices_) + static_cast<std::uint64_t>(faces_) > remaining) {
      Fail(fmt::format("{} vertices and {} faces are more than the file's {} remaining lines can hold (one line "
                       "each)",
                       vertices_, faces_, remaining));
    }
  }

  std::array<double, 3> ReadVertex(int v) {
    lines_.Next();  // there is one: ReadCounts checked
    const auto& w = lines_.words();
    const size_t base = 3 + (normal_ ? 3 : 0) + (texture_ ? 2 : 0);
    const bool fits = color_ ? (w.size() == base + 3 || w.size() == base + 4) : w.size() == base;
    if (!fits) {
      Fail(fmt::format("vertex {} has {} numbers, but {} vertices are '{}'", v, w.size(), keyword_,
                       fmt::format("x y z{}{}{}", normal_ ? " nx ny nz" : "", color_ ? " r g b [a]" : "",
                                   texture_ ? " s t" : "")));
    }
    std::array<double, 3> point{};
    for (size_t i = 0; i < w.size(); ++i) {
      const std::optional<float> value = ParseFloat(w[i]);
      if (!value) Fail(fmt::format("vertex {}: {} is not a number (or not within float range)", v, Quote(w[i])));
      if (i < 3) {
        if (!std::isfinite(*value)) {
          Fail(fmt::format("vertex {} has a non-finite {} coordinate ({})", v, "xyz"[i], Quote(w[i])));
        }
        point[i] = *value;
      }
    }
    return point;
  }

  std::vector<int> ReadFace(int f) {
    lines_.Next();
    const auto& w = lines_.words();
    const std::optional<int> corners = ParseInt(w[0]);
    if (!corners) Fail(fmt::format("face {}: the corner count {} is not a non-negative integer", f, Quote(w[0])));
    if (*corners < 3) Fail(fmt::format("face {} has {} corners", f, *corners));
    const size_t listed = w.size() - 1;
    if (listed < static_cast<size_t>(*corners)) {
      Fail(fmt::format("face {} has {} corners but lists {} vertex indices", f, *corners, listed));
    }
    // An optional colour follows the corners: a colour map index, RGB or RGBA.
    const size_t colour = listed - static_cast<size_t>(*corners);
    if (colour != 0 && colour != 1 && colour != 3 && colour != 4) {
      Fail(fmt::format("face {} has {} corners and {} more numbers; a face colour is 1, 3 or 4 numbers", f,
                       *corners, colour));
    }
    std::vector<int> polygon;
    polygon.reserve(static_cast<size_t>(*corners));
    for (size_t i = 1; i <= static_cast<size_t>(*corners); ++i) {
      const std::optional<int> index = ParseInt(w[i]);
      if (!index) Fail(fmt::format("face {}: {} is not a vertex index (0-based)", f, Quote(w[i])));
      if (*index >= vertices_) {
        Fail(fmt::format("face {} refers to vertex {}, but the file has {} vertices", f, *index, vertices_));
      }
      polygon.push_back(*index);
    }
    for (size_t i = 1 + static_cast<size_t>(*corners); i < w.size(); ++i) {
      if (!ParseFloat(w[i])) Fail(fmt::format("face {}: its colour {} is not a number", f, Quote(w[i])));
    }
    return polygon;
  }

  Lines lines_;
  const std::string& source_;
  std::string_view keyword_;
  bool texture_ = false, color_ = false, normal_ = false;
  int vertices_ = 0, faces_ = 0, counts_line_ = 0;
};

}  // namespace

PolygonSoup ReadOff(std::string_view text, const std::string& source) { return OffReader(text, source).Read(); }

}  // namespace springblend
