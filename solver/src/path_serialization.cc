// The target paths as bytes and back (target_paths.h): versioned and little-endian, written in pieces, parsed
// from memory or from a file whose fields then stay there.
#include "target_paths.h"

#include <fmt/format.h>

#include <cmath>
#include <cstring>

#include "path_internals.h"

namespace springblend::internal {

namespace {

constexpr char kPathsMagic[8] = {'S', 'B', 'P', 'A', 'T', 'H', '0', '4'};
constexpr char kPathsMagicV3[8] = {'S', 'B', 'P', 'A', 'T', 'H', '0', '3'};  // floats; still read
constexpr char kPathsMagicV2[8] = {'S', 'B', 'P', 'A', 'T', 'H', '0', '2'};  // no tangents; still read

template <typename T>
void Put(std::string* out, const T& value) {
  out->append(reinterpret_cast<const char*>(&value), sizeof(T));
}

// Reads the serialized paths from memory or from a file (whose fields are then left there: PathField::Stored).
class Cursor {
 public:
  explicit Cursor(const std::string& in) : in_(&in), size_(in.size()) {}
  Cursor(std::shared_ptr<const PathFile> file, std::int64_t offset, size_t size)
      : file_(std::move(file)), offset_(offset), size_(size) {}
  template <typename T>
  bool Get(T* value) {
    return GetBytes(value, sizeof(T));
  }
  bool GetBytes(void* out, size_t n) {
    if (n > left()) return false;
    if (n > 0) {
      if (in_ != nullptr) {
        std::memcpy(out, in_->data() + at_, n);
      } else {
        file_->Read(offset_ + static_cast<std::int64_t>(at_), n, out);
      }
    }
    at_ += n;
    return true;
  }
  size_t left() const { return size_ - at_; }
  bool GetField(Eigen::Index rows, PathField* field) {
    if (in_ != nullptr) return PathField::Parse(*in_, &at_, rows, field);
    char header[PathField::kHeaderBytes];
    double step = 0.0;
    int words = 0;
    if (rows <= 0 || !GetBytes(header, sizeof(header)) || !PathField::ParseHeader(header, &step, &words)) return false;
    const size_t words_size = sizeof(std::int32_t) * 3 * static_cast<size_t>(rows);
    if (left() / words_size < static_cast<size_t>(words)) return false;
    *field = PathField::Stored(file_, offset_ + static_cast<std::int64_t>(at_), rows, words, step);
    at_ += words_size * static_cast<size_t>(words);
    return true;
  }
  // A float field of the older versions, in fixed point (held in memory).
  bool GetFloatField(Eigen::Index rows, PathField* field) {
    Eigen::MatrixXf f(rows, 3);
    if (!GetBytes(f.data(), sizeof(float) * 3 * static_cast<size_t>(rows)) || !f.allFinite()) return false;
    *field = PathField(f.cast<double>());
    return true;
  }

 private:
  const std::string* in_ = nullptr;
  std::shared_ptr<const PathFile> file_;
  std::int64_t offset_ = 0;
  size_t size_ = 0;
  size_t at_ = 0;
};

}  // namespace

bool WriteTargetPaths(const std::vector<TargetPath>& paths, const std::function<bool(std::string_view)>& write) {
  constexpr size_t kPiece = size_t{4} << 20;  // bytes gathered before they are told
  std::string out(kPathsMagic, sizeof(kPathsMagic));
  const auto flush = [&](size_t at_least) {
    if (out.size() < at_least) return true;
    const bool ok = write(out);
    out.clear();
    return ok;
  };
  const std::uint32_t vertices = [&] {
    for (const TargetPath& p : paths) {
      if (!p.empty()) return static_cast<std::uint32_t>(p.corrections[0].rows());
    }
    return std::uint32_t{0};
  }();
  Put<std::uint32_t>(&out, static_cast<std::uint32_t>(paths.size()));
  Put<std::uint32_t>(&out, vertices);
  for (const TargetPath& p : paths) {
    Put<std::uint32_t>(&out, static_cast<std::uint32_t>(p.samples()));
    if (p.empty()) continue;
    Put<double>(&out, p.max_error);
    Put<std::int32_t>(&out, p.solves);
    Put<std::int32_t>(&out, p.newton_iterations);
    Put<std::int32_t>(&out, p.unconverged);
    for (double a : p.alphas) Put<double>(&out, a);
    out.append(reinterpret_cast<const char*>(p.breaks.data()), p.breaks.size());
    out.append(reinterpret_cast<const char*>(p.certified.data()), p.certified.size());
    // Version 4: fixed point (PathField), in one or two words.
    for (const PathField& c : p.corrections) {
      c.AppendTo(&out);
      if (!flush(kPiece)) return false;
    }
    // Version 3: per sample, whether it has an exact tangent, then those tangents.
    for (int k = 0; k < p.samples(); ++k) out.push_back(HasTangent(p, k) ? 1 : 0);
    for (int k = 0; k < p.samples(); ++k) {
      if (!HasTangent(p, k)) continue;
      p.tangents[k].AppendTo(&out);
      if (!flush(kPiece)) return false;
    }
  }
  return flush(1);
}

std::string SerializeTargetPaths(const std::vector<TargetPath>& paths) {
  std::string bytes;
  WriteTargetPaths(paths, [&](std::string_view piece) {
    bytes.append(piece);
    return true;
  });
  return bytes;
}

namespace {

std::optional<std::vector<TargetPath>> ParsePaths(Cursor& in, int targets, int vertices, std::string* why) {
  char magic[sizeof(kPathsMagic)];
  if (!in.GetBytes(magic, sizeof(magic)) || (std::memcmp(magic, kPathsMagic, sizeof(magic)) != 0 &&
                                              std::memcmp(magic, kPathsMagicV3, sizeof(magic)) != 0 &&
                                              std::memcmp(magic, kPathsMagicV2, sizeof(magic)) != 0)) {
    *why = "not target paths of a known version";
    return std::nullopt;
  }
  const bool fixed_point = std::memcmp(magic, kPathsMagic, sizeof(magic)) == 0;
  const bool with_tangents = fixed_point || std::memcmp(magic, kPathsMagicV3, sizeof(magic)) == 0;
  const auto get_field = [&](Eigen::Index n, PathField* field) {
    return fixed_point ? in.GetField(n, field) : in.GetFloatField(n, field);
  };
  std::uint32_t count = 0, rows = 0;
  if (!in.Get(&count) || !in.Get(&rows)) {
    *why = "truncated";
    return std::nullopt;
  }
  if (static_cast<int>(count) != targets) {
    *why = fmt::format("{} paths for {} targets", count, targets);
    return std::nullopt;
  }
  std::vector<TargetPath> paths(count);
  for (TargetPath& p : paths) {
    std::uint32_t samples = 0;
    if (!in.Get(&samples)) {
      *why = "truncated";
      return std::nullopt;
    }
    if (samples == 0) continue;
    if (static_cast<int>(rows) != vertices) {
      *why = fmt::format("paths of {} vertices for a rig of {}", rows, vertices);
      return std::nullopt;
    }
    // At least (every version's field takes at least a float per coordinate).
    const size_t need = samples * (sizeof(double) + 2 + sizeof(float) * 3 * static_cast<size_t>(rows));
    if (samples < 2 || need > in.left()) {
      *why = "truncated";
      return std::nullopt;
    }
    bool ok = in.Get(&p.max_error) && in.Get(&p.solves) && in.Get(&p.newton_iterations) &&
              in.Get(&p.unconverged);
    p.alphas.resize(samples);
    p.breaks.resize(samples);
    p.certified.resize(samples - 1);
    ok = ok && in.GetBytes(p.alphas.data(), sizeof(double) * samples) && in.GetBytes(p.breaks.data(), samples) &&
         in.GetBytes(p.certified.data(), samples - 1);
    for (std::uint32_t k = 0; ok && k < samples; ++k) {
      PathField c;
      ok = get_field(rows, &c);
      p.corrections.push_back(std::move(c));
    }
    p.tangents.assign(samples, PathField());
    if (ok && with_tangents) {
      std::vector<std::uint8_t> has(samples);
      ok = in.GetBytes(has.data(), samples);
      for (std::uint32_t k = 0; ok && k < samples; ++k) {
        if (has[k] > 1) ok = false;
        if (!ok || has[k] == 0) continue;
        ok = get_field(rows, &p.tangents[k]);
      }
    }
    for (std::uint32_t k = 0; ok && k + 1 < samples; ++k) {
      ok = std::isfinite(p.alphas[k]) && p.alphas[k] < p.alphas[k + 1] && p.certified[k] <= kFold;
    }
    if (!ok) {
      *why = "malformed samples";
      return std::nullopt;
    }
  }
  if (in.left() != 0) {
    *why = "trailing bytes";
    return std::nullopt;
  }
  return paths;
}

}  // namespace

std::optional<std::vector<TargetPath>> ParseTargetPaths(const std::string& bytes, int targets, int vertices,
                                                        std::string* why) {
  Cursor in(bytes);
  return ParsePaths(in, targets, vertices, why);
}

std::optional<std::vector<TargetPath>> ParseTargetPaths(std::shared_ptr<const PathFile> file, std::int64_t offset,
                                                        std::int64_t size, int targets, int vertices,
                                                        std::string* why) {
  if (size < 0) size = file->size() - offset;
  if (offset < 0 || size < 0 || offset > file->size() || size > file->size() - offset) {
    *why = fmt::format("'{}' holds {} bytes, not {} at {}", file->path(), file->size(), size, offset);
    return std::nullopt;
  }
  Cursor in(std::move(file), offset, static_cast<size_t>(size));
  return ParsePaths(in, targets, vertices, why);
}

}  // namespace springblend::internal
