#include "character_store.h"

#include <ext/stdio_filebuf.h>
#include <fcntl.h>
#include <malloc.h>
#include <openssl/evp.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <future>
#include <memory>
#include <fmt/format.h>
#include <fstream>
#include <random>
#include <unordered_set>
#include <vector>

#include "springblend/error.h"
#include "status.h"

#include <spdlog/spdlog.h>

namespace springblend::server {
namespace {

// Cache files (the layout is in character_store.h). Version 1 is only read: files of older servers.
constexpr char kFileMagicV1[8] = {'S', 'B', 'C', 'H', 'A', 'R', '0', '1'};
constexpr char kFileMagic[8] = {'S', 'B', 'C', 'H', 'A', 'R', '0', '2'};
constexpr size_t kDigestBytes = 32;  // SHA-256
// After the shapes of a production rig (in-betweens, masks, combinations); plain characters end before it.
constexpr char kRigMarker[8] = {'S', 'B', 'R', 'I', 'G', '0', '0', '1'};
// Build options beyond the defaults that change the solved frames: a byte for target paths (0: none), then,
// only when set, a byte 1 for the held outer rim. Written only when some differs from the default, so a
// character with default options keeps the bytes (and id) it always had, and files of earlier versions (the
// first byte alone) still load.
constexpr char kOptionsMarker[8] = {'S', 'B', 'O', 'P', 'T', '0', '0', '1'};

// Little-endian byte writer/reader for the canonical form (x86-64 and aarch64 are little-endian).
class Writer {
 public:
  template <typename T>
  void Put(const T& value) {
    out_.append(reinterpret_cast<const char*>(&value), sizeof(T));
  }
  void PutString(const std::string& s) {
    Put<std::uint32_t>(static_cast<std::uint32_t>(s.size()));
    out_.append(s);
  }
  void PutBytes(const void* data, size_t n) { out_.append(static_cast<const char*>(data), n); }
  std::string Take() { return std::move(out_); }

 private:
  std::string out_;
};

class Reader {
 public:
  explicit Reader(const std::string& in) : in_(in) {}
  template <typename T>
  T Get() {
    T value;
    Need(sizeof(T));
    std::memcpy(&value, in_.data() + at_, sizeof(T));
    at_ += sizeof(T);
    return value;
  }
  std::string GetString() {
    const auto n = Get<std::uint32_t>();
    Need(n);
    std::string s = in_.substr(at_, n);
    at_ += n;
    return s;
  }
  void GetBytes(void* out, size_t n) {
    Need(n);
    if (n == 0) return;  // out may be null (an empty matrix), and memcpy(nullptr, ..., 0) is undefined
    std::memcpy(out, in_.data() + at_, n);
    at_ += n;
  }
  bool Done() const { return at_ == in_.size(); }
  size_t left() const { return in_.size() - at_; }

 private:
  void Need(size_t n) const {
    if (n > in_.size() - at_) throw Error(ErrorCode::kInvalidInput, "character data is truncated");
  }
  const std::string& in_;
  size_t at_ = 0;
};

std::string Sha256(const std::string& bytes) {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  EVP_Digest(bytes.data(), bytes.size(), digest, &length, EVP_sha256(), nullptr);
  return std::string(reinterpret_cast<const char*>(digest), length);
}

// 2 or 1 for a cache file's magic, 0 for anything else.
int FileVersion(const char (&magic)[sizeof(kFileMagic)]) {
  if (std::memcmp(magic, kFileMagic, sizeof(magic)) == 0) return 2;
  if (std::memcmp(magic, kFileMagicV1, sizeof(magic)) == 0) return 1;
  return 0;
}

// Where the payload (whose first field is the name) starts in a cache file of that version.
size_t PayloadOffset(int version) {
  return sizeof(kFileMagic) + kDigestBytes + (version >= 2 ? sizeof(std::uint64_t) : 0);
}

bool ReadExactly(std::istream& in, std::uint64_t n, std::string* out) {
  out->resize(n);  // n is at most what is left of the file: the callers check it against its size
  return static_cast<bool>(in.read(out->data(), static_cast<std::streamsize>(n)));
}

// SHA-256 of bytes told in pieces (none kept); Final is empty when OpenSSL failed.
class Sha256Stream {
 public:
  Sha256Stream() : context_(EVP_MD_CTX_new(), EVP_MD_CTX_free) {
    ok_ = context_ && EVP_DigestInit_ex(context_.get(), EVP_sha256(), nullptr) == 1;
  }
  void Update(std::string_view piece) {
    ok_ = ok_ && EVP_DigestUpdate(context_.get(), piece.data(), piece.size()) == 1;
  }
  std::string Final() {
    unsigned char digest[EVP_MAX_MD_SIZE];
    unsigned int length = 0;
    if (!ok_ || EVP_DigestFinal_ex(context_.get(), digest, &length) != 1) return {};
    return std::string(reinterpret_cast<const char*>(digest), length);
  }

 private:
  std::unique_ptr<EVP_MD_CTX, decltype(&EVP_MD_CTX_free)> context_;
  bool ok_ = false;
};

// SHA-256 of the next n bytes of `in`, read in pieces (none kept); empty when they cannot be read.
std::string StreamSha256(std::istream& in, std::uint64_t n) {
  Sha256Stream sha;
  std::vector<char> piece(1 << 20);
  while (n > 0) {
    const std::uint64_t take = std::min<std::uint64_t>(n, piece.size());
    if (!in.read(piece.data(), static_cast<std::streamsize>(take))) return {};
    sha.Update(std::string_view(piece.data(), take));
    n -= take;
  }
  return sha.Final();
}

// A cache file's parts, each checked against its checksum; false (and why) when the file is not whole. The
// precomputed paths (possibly hundreds of megabytes) are checked as they are read and not kept: *precomputed
// says where they are, for the rig to read its samples from the file as frames need them.
bool ReadCacheFile(std::istream& in, std::string* payload, std::optional<CharacterStore::FilePart>* precomputed,
                   std::string* paths_digest, std::string* why) {
  in.seekg(0, std::ios::end);
  const std::uint64_t size = static_cast<std::uint64_t>(std::max<std::streamoff>(0, in.tellg()));
  in.seekg(0);
  char magic[sizeof(kFileMagic)];
  const int version = in.read(magic, sizeof(magic)) ? FileVersion(magic) : 0;
  if (version == 0) {
    *why = "not a cache file";
    return false;
  }
  const size_t offset = PayloadOffset(version);
  std::string digest;
  std::uint64_t length = size > offset ? size - offset : 0;  // version 1: the rest of the file
  if (size <= offset || !ReadExactly(in, kDigestBytes, &digest) ||
      (version >= 2 && (!in.read(reinterpret_cast<char*>(&length), sizeof(length)) ||
                        size - offset < kDigestBytes || length > size - offset - kDigestBytes))) {
    *why = "truncated";
    return false;
  }
  if (length == 0 || !ReadExactly(in, length, payload) || Sha256(*payload) != digest) {
    *why = "the character's checksum does not match";
    return false;
  }
  if (version == 1) return true;
  const std::uint64_t part_size = size - offset - length - kDigestBytes;
  if (!ReadExactly(in, kDigestBytes, &digest) || StreamSha256(in, part_size) != digest) {
    *why = "the precomputed paths' checksum does not match";
    return false;
  }
  *paths_digest = digest;
  *precomputed = CharacterStore::FilePart{static_cast<std::int64_t>(size - part_size),
                                          static_cast<std::int64_t>(part_size)};
  return true;
}

// A cache file opened for reading, once: a regular file only, never through a symbolic link, and without
// blocking (a FIFO named like a cache file held the metadata pool's thread for good). Anything else is skipped
// with a log line, and never removed. What is checked through it is what the rig then reads (file()): the name
// is never opened again, so nothing renamed over it since (a FIFO that would block the build thread) is read.
class CacheFileReader {
 public:
  explicit CacheFileReader(const std::string& path) {
    const int fd = ::open(path.c_str(), O_RDONLY | O_NOFOLLOW | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0) {
      if (errno == ELOOP) spdlog::warn("cache file {} is a symbolic link: not read", path);
      return;
    }
    auto file = std::make_shared<const OpenFile>(fd);
    struct stat status {};
    if (::fstat(fd, &status) != 0 || !S_ISREG(status.st_mode)) {
      spdlog::warn("{} is not a regular file: not read as a cache file, and left alone", path);
      return;
    }
    ::fcntl(fd, F_SETFL, ::fcntl(fd, F_GETFL) & ~O_NONBLOCK);
    const int stream_fd = ::fcntl(fd, F_DUPFD_CLOEXEC, 0);  // the stream's own (it closes it); reads share the offset
    if (stream_fd < 0) {
      spdlog::warn("cache file {} not read: {}", path, std::strerror(errno));
      return;
    }
    file_ = std::move(file);
    buffer_ = std::make_unique<__gnu_cxx::stdio_filebuf<char>>(stream_fd, std::ios::in | std::ios::binary);
    stream_ = std::make_unique<std::istream>(buffer_.get());
  }
  explicit operator bool() const { return stream_ != nullptr; }
  std::istream& stream() { return *stream_; }
  const std::shared_ptr<const OpenFile>& file() const { return file_; }

 private:
  std::shared_ptr<const OpenFile> file_;
  std::unique_ptr<__gnu_cxx::stdio_filebuf<char>> buffer_;
  std::unique_ptr<std::istream> stream_;
};

// Removes a cache file (or a symbolic link named like one, not what it points to); anything else with its name
// (a directory, a FIFO) is left alone with a log line. True when something was removed.
bool RemoveCacheFile(const std::string& path) {
  struct stat status {};
  if (::lstat(path.c_str(), &status) != 0) return false;
  if (!S_ISREG(status.st_mode) && !S_ISLNK(status.st_mode)) {
    spdlog::warn("{} is not a regular file: not removed", path);
    return false;
  }
  return ::unlink(path.c_str()) == 0;
}

// Gives the process's free heap back to the system. A rig build frees hundreds of megabytes of working memory (a
// face's: its two paths in flight, their chains' factorizations) in pieces over several allocator arenas, which
// glibc otherwise keeps: a server's resident set stayed at 253 MB after a 16-expression face's upload whose rig
// holds a few tens.
void ReturnFreeHeap() {
#if defined(__GLIBC__)
  malloc_trim(0);
#endif
}

bool WriteAll(int fd, std::string_view bytes) {
  while (!bytes.empty()) {
    const ssize_t n = ::write(fd, bytes.data(), bytes.size());
    if (n <= 0) return false;
    bytes.remove_prefix(static_cast<size_t>(n));
  }
  return true;
}

// The solver's note on precomputed paths it did not use (why), or a plain word when it left none.
std::string UnusedPathsNote(const RigSummary& summary) {
  for (const auto& note : summary.notes) {
    if (note.find("precomputed") != std::string::npos) return note;
  }
  return "the precomputed target paths were not used";
}

bool IsCancelled(const std::exception_ptr& error) {
  try {
    std::rethrow_exception(error);
  } catch (const Error& e) {
    return e.code() == ErrorCode::kCancelled;
  } catch (...) {
    return false;
  }
}

// Waits for another caller's build of the character; throws Error(kCancelled) when this caller's `stop` says
// stop first (asked every 20 ms).
double MillisecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

std::string Hex(const std::string& bytes) {
  std::string out;
  for (unsigned char c : bytes) out += fmt::format("{:02x}", c);
  return out;
}

std::string SerializeWithName(const CharacterData& d, const std::string& name) {
  Writer w;
  w.PutString(name);
  const RigOptions& o = d.options;
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(o.fixed_vertices.size()));
  for (int v : o.fixed_vertices) w.Put<std::int32_t>(v);
  w.Put<double>(o.static_tolerance);
  w.Put<std::uint8_t>(o.interior ? 1 : 0);
  w.Put<std::uint8_t>(o.anchor ? 1 : 0);
  w.Put<double>(o.bending_stiffness);
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(d.target_names.size()));
  for (const auto& t : d.target_names) w.PutString(t);
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(d.faces.rows()));
  w.PutBytes(d.faces.data(), sizeof(int) * static_cast<size_t>(d.faces.size()));
  const auto vertices = d.shapes.empty() ? 0 : d.shapes[0].rows();
  w.Put<std::uint32_t>(static_cast<std::uint32_t>(vertices));
  for (const auto& s : d.shapes) w.PutBytes(s.data(), sizeof(double) * static_cast<size_t>(s.size()));
  if (!d.target_rigs.empty()) {
    w.PutBytes(kRigMarker, sizeof(kRigMarker));
    for (const TargetRigData& t : d.target_rigs) {
      w.Put<std::uint32_t>(static_cast<std::uint32_t>(t.inbetween_weights.size()));
      for (size_t i = 0; i < t.inbetween_weights.size(); ++i) {
        w.Put<double>(t.inbetween_weights[i]);
        w.PutBytes(t.inbetweens[i].data(), sizeof(double) * static_cast<size_t>(t.inbetweens[i].size()));
      }
      w.Put<std::uint8_t>(t.mask.empty() ? 0 : 1);
      if (!t.mask.empty()) w.PutBytes(t.mask.data(), sizeof(double) * t.mask.size());  // data() may be null
      w.Put<std::uint32_t>(static_cast<std::uint32_t>(t.combination.size()));
      for (const auto& driver : t.combination) w.PutString(driver);
    }
  }
  // The options tail, written only where an option differs from the default (a character without any keeps
  // the bytes, and so the id, it always had): whether it has paths, then whether its rim is held, then the
  // paths' density.
  const RigOptions defaults;
  const bool density = o.path_intervals != defaults.path_intervals || o.path_max_samples != defaults.path_max_samples;
  if (!o.target_paths || o.hold_outer_rim || density) {
    w.PutBytes(kOptionsMarker, sizeof(kOptionsMarker));
    w.Put<std::uint8_t>(o.target_paths ? 1 : 0);
    if (o.hold_outer_rim || density) w.Put<std::uint8_t>(o.hold_outer_rim ? 1 : 0);
    if (density) {
      w.Put<std::uint32_t>(static_cast<std::uint32_t>(o.path_intervals));
      w.Put<std::uint32_t>(static_cast<std::uint32_t>(o.path_max_samples));
    }
  }
  return w.Take();
}

// A temporary of WriteFile: ID.sbchar.tmp.PID.SUFFIX, ID 64 lowercase hex digits, PID decimal, SUFFIX hex (or
// decimal, as earlier versions wrote it).
bool IsTemporaryName(const std::string& name) {
  constexpr std::string_view kMiddle = ".sbchar.tmp.";
  if (name.size() < 64 + kMiddle.size() + 3 || !CharacterStore::ValidId(name.substr(0, 64)) ||
      name.compare(64, kMiddle.size(), kMiddle) != 0) {
    return false;
  }
  const std::string rest = name.substr(64 + kMiddle.size());
  const size_t dot = rest.find('.');
  if (dot == std::string::npos || dot == 0 || dot + 1 == rest.size()) return false;
  const auto all = [](std::string_view s, std::string_view digits) {
    return s.find_first_not_of(digits) == std::string_view::npos;
  };
  return all(std::string_view(rest).substr(0, dot), "0123456789") &&
         all(std::string_view(rest).substr(dot + 1), "0123456789abcdef");
}

std::uint64_t RandomSuffix() {
  thread_local std::mt19937_64 generator{std::random_device{}()};
  return generator();
}

std::int64_t EstimateBytes(const Rig& rig) {
  const std::int64_t n = rig.num_vertices(), m = rig.num_springs(), shapes = rig.num_shapes() + 1;
  // The target paths held in memory count (those left in a cache file do not: RigSummary::path_file_bytes).
  return 24 * n * shapes * 2 + m * (9 + 8 * shapes) + rig.summary().hessian_nonzeros * 16 +
         rig.summary().faces * 12LL * shapes + rig.summary().path_bytes;
}

}  // namespace

std::string Serialize(const CharacterData& data) { return SerializeWithName(data, data.name); }

std::string ContentId(const CharacterData& data) { return Hex(Sha256(SerializeWithName(data, ""))); }

CharacterData Deserialize(const std::string& bytes) {
  Reader r(bytes);
  CharacterData d;
  d.name = r.GetString();
  const auto fixed = r.Get<std::uint32_t>();
  if (fixed > bytes.size()) throw Error(ErrorCode::kInvalidInput, "character data: bad fixed vertex count");
  for (std::uint32_t i = 0; i < fixed; ++i) d.options.fixed_vertices.push_back(r.Get<std::int32_t>());
  d.options.static_tolerance = r.Get<double>();
  d.options.interior = r.Get<std::uint8_t>() != 0;
  d.options.anchor = r.Get<std::uint8_t>() != 0;
  d.options.bending_stiffness = r.Get<double>();
  const auto targets = r.Get<std::uint32_t>();
  if (targets > bytes.size()) throw Error(ErrorCode::kInvalidInput, "character data: bad target count");
  for (std::uint32_t t = 0; t < targets; ++t) d.target_names.push_back(r.GetString());
  const auto faces = r.Get<std::uint32_t>();
  if (static_cast<size_t>(faces) * 12 > bytes.size()) throw Error(ErrorCode::kInvalidInput, "character data: bad face count");
  d.faces.resize(faces, 3);
  r.GetBytes(d.faces.data(), sizeof(int) * 3 * static_cast<size_t>(faces));
  const auto vertices = r.Get<std::uint32_t>();
  if (static_cast<size_t>(vertices) * 24 * (targets + 1) > bytes.size()) {
    throw Error(ErrorCode::kInvalidInput, "character data: bad vertex count");
  }
  for (std::uint32_t s = 0; s <= targets; ++s) {
    Points p(vertices, 3);
    r.GetBytes(p.data(), sizeof(double) * 3 * static_cast<size_t>(vertices));
    d.shapes.push_back(std::move(p));
  }
  char marker[sizeof(kRigMarker)] = {};
  if (!r.Done()) r.GetBytes(marker, sizeof(marker));
  if (std::memcmp(marker, kRigMarker, sizeof(marker)) == 0) {
    for (std::uint32_t t = 0; t < targets; ++t) {
      TargetRigData rig;
      const auto inbetweens = r.Get<std::uint32_t>();
      if (static_cast<size_t>(inbetweens) * (8 + 24 * static_cast<size_t>(vertices)) > r.left()) {
        throw Error(ErrorCode::kInvalidInput, "character data: bad in-between count");
      }
      for (std::uint32_t i = 0; i < inbetweens; ++i) {
        rig.inbetween_weights.push_back(r.Get<double>());
        Points p(vertices, 3);
        r.GetBytes(p.data(), sizeof(double) * 3 * static_cast<size_t>(vertices));
        rig.inbetweens.push_back(std::move(p));
      }
      if (r.Get<std::uint8_t>() != 0) {
        rig.mask.resize(vertices);
        r.GetBytes(rig.mask.data(), sizeof(double) * static_cast<size_t>(vertices));
      }
      const auto drivers = r.Get<std::uint32_t>();
      if (drivers > r.left()) throw Error(ErrorCode::kInvalidInput, "character data: bad combination count");
      for (std::uint32_t i = 0; i < drivers; ++i) rig.combination.push_back(r.GetString());
      d.target_rigs.push_back(std::move(rig));
    }
    std::memset(marker, 0, sizeof(marker));
    if (!r.Done()) r.GetBytes(marker, sizeof(marker));
  }
  if (std::memcmp(marker, kOptionsMarker, sizeof(marker)) == 0) {
    d.options.target_paths = r.Get<std::uint8_t>() != 0;
    if (!r.Done()) d.options.hold_outer_rim = r.Get<std::uint8_t>() != 0;
    if (!r.Done()) {
      d.options.path_intervals = static_cast<int>(r.Get<std::uint32_t>());
      d.options.path_max_samples = static_cast<int>(r.Get<std::uint32_t>());
      d.options.Validate();  // a file's options are checked as an upload's (Error kInvalidInput names them)
    }
  } else if (marker[0] != 0) {
    throw Error(ErrorCode::kInvalidInput, "character data has trailing bytes");
  }
  if (!r.Done()) throw Error(ErrorCode::kInvalidInput, "character data has trailing bytes");
  return d;
}

CharacterStore::CharacterStore(StoreOptions options) : options_(std::move(options)) {
  // spdlog's registry is a function-local static of the (uninstrumented) library: construct it here, before
  // the store's callers log from several threads, so its first use is not a race ThreadSanitizer reports.
  spdlog::default_logger_raw();
  if (!options_.directory.empty()) {
    std::error_code ec;
    std::filesystem::create_directories(options_.directory, ec);
    if (ec) throw Error(ErrorCode::kInvalidInput, "cannot create the cache directory " + options_.directory + ": " + ec.message());
    // A directory we cannot write serves what it holds, but keeps nothing new: say so now, not at each upload.
    const std::string probe = fmt::format("{}/.springblend-write-test.{}.{:016x}", options_.directory, ::getpid(),
                                          RandomSuffix());
    const int fd = ::open(probe.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC, 0600);
    if (fd < 0) {
      spdlog::warn("the cache directory {} is not writable ({}): uploads will be served from memory only, not kept "
                   "for restarts or other replicas",
                   options_.directory, std::strerror(errno));
    } else {
      ::close(fd);
      ::unlink(probe.c_str());
    }
  }
  if (options_.build_threads < 1 || options_.build_queue < 0) {
    throw Error(ErrorCode::kInvalidInput, "the store needs at least one build thread and a queue of 0 or more");
  }
  builds_ = std::make_unique<SolverPool>(options_.build_threads, options_.build_queue);
}

CharacterStore::~CharacterStore() { builds_.reset(); }

CharacterStore::PendingBuild::PendingBuild(std::string id, bool from_file, std::string name)
    : id_(std::move(id)), name_(std::move(name)), created_(std::chrono::steady_clock::now()) {
  progress_.rig.stage = "queued";
  progress_.from_file = from_file;
}

BuildProgress CharacterStore::PendingBuild::progress() const {
  std::lock_guard lock(mutex_);
  BuildProgress p = progress_;
  p.rig.elapsed_ms = MillisecondsSince(created_);  // now, not at the last report (a stage can take minutes)
  return p;
}

void CharacterStore::PendingBuild::Report(const RigBuildProgress& progress) {
  std::lock_guard lock(mutex_);
  progress_.rig = progress;
  // The paths are most of a build, and take about as long per target: the rest is extrapolated from them.
  if (progress.stage == "paths" && paths_began_ms_ < 0) paths_began_ms_ = progress.elapsed_ms;
  if (progress.stage == "paths" && progress.targets_done > 0 && progress.targets > 0) {
    progress_.estimate_ms = paths_began_ms_ + (progress.elapsed_ms - paths_began_ms_) * progress.targets /
                                                  progress.targets_done;
  } else if (progress.stage == "done") {
    progress_.estimate_ms = progress.elapsed_ms;
  }
}

void CharacterStore::PendingBuild::OnDone(Done done) {
  std::unique_lock lock(mutex_);
  if (!ended_) {
    done_.push_back(std::move(done));
    return;
  }
  lock.unlock();
  done(entry_, error_);
}

void CharacterStore::PendingBuild::End(std::shared_ptr<const Entry> entry, std::exception_ptr error) {
  std::vector<Done> done;
  {
    std::lock_guard lock(mutex_);
    entry_ = std::move(entry);
    error_ = error;
    ended_ = true;
    done.swap(done_);
  }
  for (Done& d : done) d(entry_, error_);
}

bool CharacterStore::ValidId(const std::string& id) {
  if (id.size() != 64) return false;
  for (char c : id) {
    if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
  }
  return true;
}

std::string CharacterStore::PathOf(const std::string& id) const {
  return (std::filesystem::path(options_.directory) / (id + ".sbchar")).string();
}

std::optional<PrecomputedLocation> CharacterStore::WriteFile(const std::string& id, const std::string& payload,
                                                             const PrecomputedWriter& precomputed, Written* written,
                                                             const std::string& expected) {
  if (options_.directory.empty()) return std::nullopt;
  // Atomic: a uniquely named temporary file, flushed to disk, then renamed over the final name. Readers see
  // the whole file or none; a crash leaves at most a temporary file, which is never read, and which the next
  // start removes (RemoveStaleTemporaries). The writer holds a lock on its temporary until the rename, so a
  // replica starting on the same directory can tell a live writer's file from a dead one's.
  const std::string path = PathOf(id);
  std::string temporary;
  int fd = -1;
  for (int attempt = 0; attempt < 3 && fd < 0; ++attempt) {
    temporary = fmt::format("{}.tmp.{}.{:016x}", path, ::getpid(), RandomSuffix());
    // Read-write: the rig reads its paths back through this descriptor, never by the name.
    fd = ::open(temporary.c_str(), O_RDWR | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC, 0644);
    if (fd < 0) {
      if (errno == EEXIST) continue;
      // The cache directory is an optimisation; serving goes on from memory, said and counted.
      ++write_failures_;
      const std::string why = fmt::format("cannot create {} ({})", temporary, std::strerror(errno));
      spdlog::warn("cache file {} not written: {}; the character is served from memory only", path, why);
      if (written != nullptr) written->failure = why;
      return std::nullopt;
    }
    // A starting replica may have opened the new file in the moment before the lock: it then holds the lock
    // or has already unlinked the file. Either way, start over under another name. (A file system without
    // locks fails with another error: write unlocked; the clean-up then leaves the file alone.)
    struct stat status {};
    if ((::flock(fd, LOCK_EX | LOCK_NB) != 0 && errno == EWOULDBLOCK) ||
        (::fstat(fd, &status) == 0 && status.st_nlink == 0)) {
      ::close(fd);
      fd = -1;
    }
  }
  if (fd < 0) {
    if (written != nullptr) written->failure = "no temporary file could be made";
    return std::nullopt;
  }
  const std::uint64_t length = payload.size();
  std::string header(kFileMagic, sizeof(kFileMagic));
  header += Sha256(payload);
  header.append(reinterpret_cast<const char*>(&length), sizeof(length));
  // The parts one after the other rather than joined, and the paths (possibly hundreds of megabytes, left by the
  // build in its spool) in pieces, hashed as they go: their checksum, which precedes them, is written last.
  const std::int64_t digest_at = static_cast<std::int64_t>(header.size() + payload.size());
  Sha256Stream sha;
  std::int64_t part_size = 0;
  std::string failure;
  std::exception_ptr lost;  // the rig's own paths could not be read back (DataLossError): the caller's to handle
  bool ok = WriteAll(fd, header) && WriteAll(fd, payload) && WriteAll(fd, std::string(kDigestBytes, '\0'));
  try {
    ok = ok && precomputed([&](std::string_view piece) {
      sha.Update(piece);
      part_size += static_cast<std::int64_t>(piece.size());
      return WriteAll(fd, piece);
    });
  } catch (const DataLossError& e) {
    ok = false;
    failure = e.what();
    lost = std::current_exception();
  } catch (const std::exception& e) {
    ok = false;
    failure = e.what();
  }
  const std::string digest = ok ? sha.Final() : std::string();
  if (ok && !expected.empty() && digest != expected) {
    ok = false;
    failure = "the rig's paths read back are not those it was built with: its file was changed in place";
    lost = std::make_exception_ptr(DataLossError(failure));
  }
  ok = ok && digest.size() == kDigestBytes &&
       ::pwrite(fd, digest.data(), kDigestBytes, static_cast<off_t>(digest_at)) ==
           static_cast<ssize_t>(kDigestBytes) &&
       ::fsync(fd) == 0;
  if (!ok || std::rename(temporary.c_str(), path.c_str()) != 0) {
    ++write_failures_;
    if (failure.empty()) failure = std::strerror(errno);
    spdlog::warn("cache file {} not written ({}); the character is served from memory only", path, failure);
    if (written != nullptr) written->failure = failure;
    ::unlink(temporary.c_str());
    ::close(fd);
    if (lost) std::rethrow_exception(lost);
    return std::nullopt;
  }
  ::flock(fd, LOCK_UN);  // after the rename; the descriptor stays open for the rig to read its paths through
  if (written != nullptr) written->paths_digest = digest;
  Remember(id, fd);
  return PrecomputedLocation{path, digest_at + static_cast<std::int64_t>(kDigestBytes), part_size,
                             std::make_shared<const OpenFile>(fd)};
}

std::optional<PrecomputedLocation> CharacterStore::WriteFile(const std::string& id, const std::string& payload,
                                                             const Rig& rig, Written* written,
                                                             const std::string& expected) {
  return WriteFile(
      id, payload, [&rig](const std::function<bool(std::string_view)>& write) { return rig.WritePrecomputed(write); },
      written, expected);
}

void CharacterStore::Remember(const std::string& id, int fd) {
  struct stat status {};
  const bool known = ::fstat(fd, &status) == 0;
  std::lock_guard lock(mutex_);
  if (known) {
    verified_[id] = FileStamp::Of(status);
  } else {
    verified_.erase(id);
  }
}

bool CharacterStore::Verified(const std::string& id) {
  struct stat status {};
  if (::lstat(PathOf(id).c_str(), &status) != 0 || !S_ISREG(status.st_mode)) return false;
  std::lock_guard lock(mutex_);
  const auto it = verified_.find(id);
  return it != verified_.end() && it->second == FileStamp::Of(status);
}

CharacterStore::Cleanup CharacterStore::RemoveStaleTemporaries() {
  Cleanup cleanup;
  if (options_.directory.empty()) return cleanup;
  namespace fs = std::filesystem;
  std::error_code ec;
  for (fs::directory_iterator it(options_.directory, ec), end; !ec && it != end; it.increment(ec)) {
    const fs::path file = it->path();
    if (!IsTemporaryName(file.filename().string())) continue;
    // O_NOFOLLOW: a symbolic link with our name is not ours (and what it points to never is). Read-write: NFS
    // grants an exclusive lock only on a file open for writing.
    const int fd = ::open(file.c_str(), O_RDWR | O_NOFOLLOW | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0) continue;
    struct stat opened {};
    if (::fstat(fd, &opened) != 0 || !S_ISREG(opened.st_mode)) {
      ::close(fd);
      continue;
    }
    if (::flock(fd, LOCK_EX | LOCK_NB) != 0) {
      if (errno == EWOULDBLOCK) ++cleanup.in_use;  // other errors: no locks here, so no telling; keep it
      ::close(fd);
      continue;
    }
    // Unlink only if the name still is the file we locked (its writer may have renamed it into place since).
    struct stat named {};
    if (::lstat(file.c_str(), &named) == 0 && named.st_dev == opened.st_dev && named.st_ino == opened.st_ino &&
        ::unlink(file.c_str()) == 0) {
      ++cleanup.removed;
    }
    ::close(fd);
  }
  return cleanup;
}

std::optional<CharacterStore::CacheFile> CharacterStore::ReadFile(const std::string& id) {
  if (options_.directory.empty()) return std::nullopt;
  CacheFileReader reader(PathOf(id));
  if (!reader) return std::nullopt;
  std::istream& in = reader.stream();
  CacheFile file;
  std::string why;
  bool ok = ReadCacheFile(in, &file.payload, &file.precomputed, &file.paths_digest, &why);
  if (ok) {
    try {
      file.data = Deserialize(file.payload);
      ok = ContentId(file.data) == id;
    } catch (const Error&) {
      ok = false;
    }
    if (!ok) why = "the content does not match its id";
  }
  if (!ok) {
    // Never serve a corrupt file: drop it; the next upload writes it anew.
    {
      std::lock_guard lock(mutex_);
      ++stats_.corrupt_files;
      verified_.erase(id);
    }
    in.clear();
    in.seekg(0, std::ios::end);
    const std::streamoff size = in.tellg();
    const bool removed = RemoveCacheFile(PathOf(id));
    spdlog::warn("cache file {} is corrupt ({} bytes, {}): {}", PathOf(id), size, why,
                 removed ? "removed" : "could not be removed");
    return std::nullopt;
  }
  file.opened = reader.file();
  Remember(id, file.opened->fd());
  return file;
}

std::shared_ptr<CharacterStore::Entry> CharacterStore::Build(const std::string& id, const CharacterData& data,
                                                                   const RigBuildControl& control) {
  {
    std::lock_guard lock(mutex_);
    ++stats_.builds;
  }
  TriangleMesh rest;
  rest.name = "rest";
  rest.source = data.name.empty() ? "rest mesh" : data.name + ": rest mesh";
  rest.vertices = data.shapes[0];
  rest.faces = data.faces;
  const auto shape = [&](const Points& vertices, const std::string& name, const std::string& source) {
    TriangleMesh mesh;
    mesh.name = name;
    mesh.source = source;
    mesh.vertices = vertices;
    mesh.faces = data.faces;
    return mesh;
  };
  auto entry = std::make_shared<Entry>();
  entry->id = id;
  entry->name = data.name;
  // Plain targets too are specs (name and mesh), as Rig::Build makes them: only that overload takes a control.
  std::vector<TargetSpec> targets;
  for (size_t t = 0; t < data.target_names.size(); ++t) {
    const std::string& name = data.target_names[t];
    TargetSpec spec;
    spec.name = name;
    spec.mesh = shape(data.shapes[t + 1], name, fmt::format("target '{}'", name));
    if (!data.target_rigs.empty()) {
      const TargetRigData& rig = data.target_rigs[t];
      for (size_t i = 0; i < rig.inbetweens.size(); ++i) {
        spec.inbetweens.push_back({rig.inbetween_weights[i],
                                   shape(rig.inbetweens[i], name, fmt::format("target '{}': inbetweens[{}]", name, i))});
      }
      spec.mask = rig.mask;
      spec.combination = rig.combination;
    }
    targets.push_back(std::move(spec));
  }
  entry->rig = Rig::Build(std::move(rest), std::move(targets), data.options, control);
  entry->bytes = EstimateBytes(*entry->rig);
  return entry;
}

void CharacterStore::Insert(std::shared_ptr<const Entry> entry) {
  const std::string id = entry->id;
  if (entries_.count(id) != 0) return;
  lru_.push_front(id);
  stats_.bytes += entry->bytes;
  entries_[id] = Slot{std::move(entry), lru_.begin()};
  stats_.characters = static_cast<std::int64_t>(entries_.size());
  Trim();
}

void CharacterStore::Trim() {
  // Someone besides the store holding an entry or its rig (an open Solve stream or Interactive session, a
  // Solver) keeps it alive: evicting it would free nothing, and the next call for it would build a second copy
  // beside the first, which the budget would no longer count. Such entries stay (counted) until they are free.
  const auto in_use = [](const std::shared_ptr<const Entry>& entry) {
    return entry.use_count() > 1 || entry->rig.use_count() > 1;
  };
  // The least recently used first, never the most recently used one.
  std::vector<std::string> victims;
  std::int64_t bytes = stats_.bytes;
  for (auto it = lru_.rbegin(); bytes > options_.memory_budget_bytes && std::next(it) != lru_.rend(); ++it) {
    const std::shared_ptr<const Entry>& entry = entries_.at(*it).entry;
    if (in_use(entry)) continue;
    victims.push_back(*it);
    bytes -= entry->bytes;
  }
  for (const std::string& victim : victims) {
    Erase(entries_.find(victim));
    ++stats_.evictions;
  }
}

std::shared_ptr<const CharacterStore::Entry> CharacterStore::Rebuild(const std::string& id, const CacheFile& file,
                                                                     const RigBuildControl& build) {
  const std::string path = PathOf(id);
  if (!file.precomputed) spdlog::info("cache file {} has no precomputed paths (version 1): rebuilding them", path);
  RigBuildControl control = build;
  if (file.precomputed) {
    // The paths stay in the file, read as frames need them: the character's memory does not grow with its
    // expressions. The file is replaced only by renaming, so the one opened keeps what was checked.
    // Read through the descriptor the file was checked through: its name is never opened again.
    control.precomputed_file =
        PrecomputedLocation{path, file.precomputed->offset, file.precomputed->size, file.opened};
  }
  // Paths solved here (an older file's, or ones that did not fit) are written at once and read from the file.
  bool written = false;
  Written write;
  control.spool_directory = options_.directory;
  control.persist = [&](const PrecomputedWriter& bytes) {
    written = true;
    return WriteFile(id, file.payload, bytes, &write);
  };
  auto entry = Build(id, file.data, control);
  const RigSummary& summary = entry->rig->summary();
  const bool unused = file.precomputed && file.data.options.target_paths && !summary.paths_loaded;
  if (unused) spdlog::warn("cache file {}: {}; rewriting the file", path, UnusedPathsNote(summary));
  spdlog::info("rebuilt {} from the cache directory in {:.0f} ms, target paths {}", id.substr(0, 12),
               summary.precompute_ms,
               summary.paths_loaded              ? "loaded from the file"
               : file.data.options.target_paths ? fmt::format("solved ({:.0f} ms)", summary.path_ms)
                                                 : std::string("off"));
  // Written once, so the next restart (or another replica) loads what this one had to solve.
  if ((!file.precomputed || unused) && !written) WriteFile(id, file.payload, *entry->rig, &write);
  entry->paths_digest = summary.paths_loaded ? file.paths_digest : write.paths_digest;
  std::lock_guard lock(mutex_);
  if (summary.paths_loaded) ++stats_.paths_loaded;
  if (!file.precomputed || unused) ++stats_.upgraded_files;
  return entry;
}

std::pair<std::shared_ptr<const CharacterStore::Entry>, bool> CharacterStore::Put(const CharacterData& data,
                                                                                   const StopCheck& stop) {
  // Twice at most: a rebuild this joined may find its file corrupt (and remove it); then `data` is built.
  for (int attempt = 0;; ++attempt) {
    Found found = Start(data, [&stop] { return !(stop && stop()); });
    const bool known = found.known;
    const bool joined = found.building != nullptr;
    auto entry = Wait(std::move(found), stop);
    if (entry || !joined || attempt == 1) return {entry, known};
  }
}

std::shared_ptr<const CharacterStore::Entry> CharacterStore::Get(const std::string& id, const StopCheck& stop) {
  if (!ValidId(id)) return nullptr;
  return Wait(Find(id, true, [&stop] { return !(stop && stop()); }), stop);
}

std::shared_ptr<const CharacterStore::Entry> CharacterStore::Wait(Found found, const StopCheck& stop) {
  if (!found.building) return found.entry;
  auto result = std::make_shared<std::promise<std::shared_ptr<const Entry>>>();
  auto future = result->get_future();
  found.building->OnDone([result](const std::shared_ptr<const Entry>& entry, std::exception_ptr error) {
    if (error) {
      result->set_exception(error);
    } else {
      result->set_value(entry);
    }
  });
  while (future.wait_for(std::chrono::milliseconds(stop ? 20 : 1000)) != std::future_status::ready) {
    if (stop && stop()) throw Error(ErrorCode::kCancelled, "stopped waiting for the character's build");
  }
  return future.get();
}

CharacterStore::Found CharacterStore::Find(const std::string& id, bool rebuild, Wants wants) {
  if (!ValidId(id)) return {};
  return Lookup(id, nullptr, rebuild, std::move(wants));
}

CharacterStore::Found CharacterStore::Start(CharacterData data, Wants wants) {
  const std::string id = ContentId(data);
  Found found = Lookup(id, &data, true, wants);  // `data` is taken only when a build starts
  // A character in memory is answered with its cache file whole: another replica sharing the directory may have
  // deleted it, or someone damaged it, since this one wrote it. A rig that cannot give its paths back as they
  // were is dropped, and built anew.
  if (found.entry && !KeepFile(found.entry, data)) found = Lookup(id, &data, true, std::move(wants));
  return found;
}

bool CharacterStore::KeepFile(const std::shared_ptr<const Entry>& entry, const CharacterData& data) {
  const std::string& id = entry->id;
  if (options_.directory.empty() || Verified(id) || ReadFile(id)) return true;
  // Missing, or corrupt (ReadFile removed it and said why): written anew from the rig in memory.
  std::string why;
  try {
    if (WriteFile(id, Serialize(data), *entry->rig, nullptr, entry->paths_digest)) {
      spdlog::warn("cache file {} was missing or damaged: written anew from the character in memory", PathOf(id));
    }
    return true;  // or could not be written (said and counted): served from memory, as after any failed write
  } catch (const DataLossError& e) {
    why = e.what();
  }
  Drop(entry, why);
  return false;
}

bool CharacterStore::Drop(const std::shared_ptr<const Entry>& entry, const std::string& why) {
  {
    std::lock_guard lock(mutex_);
    verified_.erase(entry->id);  // checked again before it is listed or read
    const auto it = entries_.find(entry->id);
    if (it == entries_.end() || it->second.entry != entry) return false;
    Erase(it);
  }
  spdlog::warn("character {} '{}' dropped from memory: its rig is damaged ({}); the next upload, or the next call "
               "that needs it, builds it anew",
               entry->id.substr(0, 12), entry->name, why);
  return true;
}

void CharacterStore::Erase(std::unordered_map<std::string, Slot>::iterator it) {
  stats_.bytes -= it->second.entry->bytes;
  lru_.erase(it->second.position);
  entries_.erase(it);
  stats_.characters = static_cast<std::int64_t>(entries_.size());
}

CharacterStore::Found CharacterStore::Lookup(const std::string& id, CharacterData* data, bool rebuild,
                                             Wants wants) {
  // Registers the caller as a waiter of `flight` (with the lock held: a build only sees no waiter under it).
  const auto join = [&wants](const std::shared_ptr<PendingBuild>& flight) {
    std::lock_guard lock(flight->mutex_);
    const auto at = flight->waiters_.insert(flight->waiters_.end(), std::move(wants));
    return Waiter(static_cast<void*>(flight.get()), [flight, at](void*) {
      std::lock_guard waiters(flight->mutex_);
      flight->waiters_.erase(at);
    });
  };
  Found found;
  std::shared_ptr<const CharacterData> own;
  std::unique_lock lock(mutex_);
  if (auto it = entries_.find(id); it != entries_.end()) {
    lru_.splice(lru_.begin(), lru_, it->second.position);
    ++stats_.hits;
    found.entry = it->second.entry;
    Trim();  // entries in use when the budget was last exceeded may be free now (this one is held: it stays)
    return found;
  }
  Trim();
  ++stats_.misses;
  if (auto other = building_.find(id); other != building_.end()) {
    found.building = other->second;
    found.waiter = join(other->second);
    found.joined = true;
    return found;
  }
  // The file is read (and checked) on the build thread: here only whether there is one.
  std::error_code ec;
  const bool on_disk = !options_.directory.empty() && std::filesystem::is_regular_file(PathOf(id), ec);
  if (!on_disk && data == nullptr) return found;
  if (on_disk && !rebuild) {
    found.stored = true;
    return found;
  }
  found.known = on_disk;
  auto flight = std::make_shared<PendingBuild>(id, on_disk, data != nullptr ? data->name : std::string());
  // An upload's data is kept even when the file is there: a corrupt file is then built from it.
  if (data != nullptr) own = std::make_shared<const CharacterData>(std::move(*data));
  found.building = flight;
  found.waiter = join(flight);
  building_[id] = flight;
  if (!builds_->TrySubmit([this, flight, own] { RunBuild(flight, own); })) {
    building_.erase(id);
    throw LimitError(fmt::format("the server's build queue is full ({} builds wait for {} build threads); retry "
                                 "later or raise --build-queue / --build-workers",
                                 builds_->queue_depth(), builds_->threads()));
  }
  return found;
}

bool CharacterStore::Abandoned(const std::shared_ptr<PendingBuild>& flight) {
  if (options_.stop && options_.stop()) return true;
  std::lock_guard lock(mutex_);
  {
    std::lock_guard own(flight->mutex_);
    for (const Wants& wants : flight->waiters_) {
      if (!wants || wants()) return false;
    }
  }
  // Nobody wants it: out of building_ now, so whoever comes next starts a build rather than join this one.
  if (auto it = building_.find(flight->id()); it != building_.end() && it->second == flight) building_.erase(it);
  return true;
}

void CharacterStore::RunBuild(const std::shared_ptr<PendingBuild>& flight,
                              const std::shared_ptr<const CharacterData>& data) {
  const std::string& id = flight->id();
  RigBuildControl control;
  control.stop = [this, flight] { return Abandoned(flight); };
  control.progress = [flight](const RigBuildProgress& progress) { flight->Report(progress); };
  std::shared_ptr<const Entry> entry;
  std::exception_ptr error;
  bool rebuilt = false;
  bool written = false;  // this upload's cache file
  Written write;         // how it went
  try {
    if (control.stop()) throw Error(ErrorCode::kCancelled, "the rig build was cancelled");
    if (flight->progress_.from_file) {
      if (const auto file = ReadFile(id)) {
        entry = Rebuild(id, *file, control);
        rebuilt = true;
      }
    }
    if (!entry && data != nullptr) {
      // The cache file is written as soon as the paths are solved, and the rig reads their samples from it
      // (RigBuildControl::persist): an uploaded character holds no more memory than a restarted one.
      const std::string payload = Serialize(*data);
      control.spool_directory = options_.directory;  // each path out of memory as soon as it is solved
      control.persist = [&](const PrecomputedWriter& bytes) {
        written = true;
        return WriteFile(id, payload, bytes, &write);
      };
      auto built = Build(id, *data, control);  // throws Error for bad meshes, or when stopped; nothing is stored then
      if (!written) WriteFile(id, payload, *built->rig, &write);
      built->paths_digest = write.paths_digest;
      if (!options_.directory.empty() && !write.failure.empty()) {
        built->not_persisted = "its cache file could not be written (" + write.failure + ")";
      }
      entry = std::move(built);
    }
  } catch (...) {
    error = std::current_exception();
  }
  // A build that failed after its file was written keeps nothing.
  if (error && written && !rebuilt && !options_.directory.empty()) RemoveCacheFile(PathOf(id));
  const bool cancelled = error && IsCancelled(error);
  if (cancelled) spdlog::info("the build of {} was stopped: nothing kept", id.substr(0, 12));
  {
    std::lock_guard lock(mutex_);
    if (auto it = building_.find(id); it != building_.end() && it->second == flight) building_.erase(it);
    if (cancelled) ++stats_.cancelled_builds;
    if (entry && !flight->deleted_) {
      if (rebuilt) ++stats_.rebuilds_from_disk;
      Insert(entry);
    }
    // A delete that came while this built has removed the file already, or found none: this build wrote it
    // afterwards, and it goes, unless an upload since (a build of its own, or its result) owns the file now.
    // Under the lock: such a build registers (in building_) before it writes anything.
    if (flight->deleted_ && !options_.directory.empty() && building_.count(id) == 0 && entries_.count(id) == 0) {
      verified_.erase(id);
      RemoveCacheFile(PathOf(id));
    }
  }
  flight->End(std::move(entry), error);
  ReturnFreeHeap();  // the build's working memory, whether it succeeded or not
}

std::vector<CharacterStore::Listed> CharacterStore::List() {
  std::vector<Listed> out;
  std::unordered_set<std::string> seen;
  {
    std::lock_guard lock(mutex_);
    for (const auto& id : lru_) {
      const auto& entry = entries_[id].entry;
      out.push_back({id, entry->name, entry});
      seen.insert(id);
    }
    for (const auto& [id, flight] : building_) {
      if (seen.count(id) != 0) continue;
      out.push_back({id, flight->name(), nullptr, flight});
      seen.insert(id);
    }
  }
  if (options_.directory.empty()) return out;
  std::error_code ec;
  for (const auto& file : std::filesystem::directory_iterator(options_.directory, ec)) {
    const std::string id = file.path().stem().string();
    if (file.path().extension() != ".sbchar" || !ValidId(id) || seen.count(id) != 0) continue;
    // Checked in full once per file version, so a corrupt file is removed (and logged) here rather than
    // listed until someone asks for it.
    if (!Verified(id) && !ReadFile(id)) continue;
    // The name is the payload's first field: read just the header, not the meshes.
    CacheFileReader reader(file.path().string());
    if (!reader) continue;
    std::istream& in = reader.stream();
    char magic[sizeof(kFileMagic)];
    const int version = in.read(magic, sizeof(magic)) ? FileVersion(magic) : 0;
    std::uint32_t length = 0;
    if (version == 0 || !in.seekg(static_cast<std::streamoff>(PayloadOffset(version))) ||
        !in.read(reinterpret_cast<char*>(&length), sizeof(length))) {
      continue;
    }
    std::string name(std::min<std::uint32_t>(length, 256), '\0');
    in.read(name.data(), static_cast<std::streamsize>(name.size()));
    out.push_back({id, name, nullptr});
  }
  return out;
}

bool CharacterStore::Delete(const std::string& id) {
  if (!ValidId(id)) return false;
  bool found = false;
  {
    std::lock_guard lock(mutex_);
    verified_.erase(id);
    if (auto flight = building_.find(id); flight != building_.end()) {
      // Finished for its callers, but not kept; and out of building_ now, so an upload that comes after this
      // delete starts a build of its own rather than join this one (and end without its character).
      flight->second->deleted_ = true;
      building_.erase(flight);
      found = true;
    }
    if (auto it = entries_.find(id); it != entries_.end()) {
      Erase(it);
      found = true;
    }
  }
  if (!options_.directory.empty()) found = RemoveCacheFile(PathOf(id)) || found;
  return found;
}

StoreStats CharacterStore::stats() const {
  std::lock_guard lock(mutex_);
  StoreStats stats = stats_;
  stats.write_failures = write_failures_.load();
  stats.build_threads = builds_->threads();
  stats.builds_running = builds_->busy();
  stats.builds_queued = builds_->queue_depth();
  return stats;
}

}  // namespace springblend::server
