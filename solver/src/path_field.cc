#include "path_field.h"

#include <fcntl.h>
#include <fmt/format.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <vector>

#include "springblend/error.h"
#include "springblend/open_files.h"
#include "springblend/rig.h"

namespace springblend::internal {
namespace {

constexpr double kHighSteps = 2147483647.0;         // 2^31 - 1: the largest magnitude's steps
constexpr double kLowScale = 4294967296.0;          // 2^32 low steps per high step
constexpr double kLowMax = 2147483647.0;

// The open path files with a name: the most recently read first, at most `limit` (0: any number).
struct PathFileRegistry {
  std::mutex mutex;
  std::list<const PathFile*> open;
  int limit = 0;
};

PathFileRegistry& Registry() {
  static auto* registry = new PathFileRegistry;  // never destroyed: rigs may outlive static destructors
  return *registry;
}

}  // namespace

void PathFile::Track(std::uint64_t device, std::uint64_t inode) {
  device_ = device;
  inode_ = inode;
  tracked_ = true;
  PathFileRegistry& registry = Registry();
  std::lock_guard lock(registry.mutex);
  registry.open.push_front(this);
  position_ = registry.open.begin();
  CloseIdle();
}

void PathFile::CloseIdle() {
  PathFileRegistry& registry = Registry();
  if (registry.limit <= 0) return;
  size_t open = registry.open.size();
  for (auto it = registry.open.end(); open > static_cast<size_t>(registry.limit) && it != registry.open.begin();) {
    --it;
    const PathFile* file = *it;
    if (file->readers_ > 0) continue;
    ::close(file->fd_);
    file->fd_ = -1;
    it = registry.open.erase(it);
    --open;
  }
}

int PathFile::Reopen() const {
  const int fd = ::open(path_.c_str(), O_RDONLY | O_NOFOLLOW | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) {
    throw DataLossError(fmt::format("target paths file '{}': cannot open it again ({}; it was closed while more "
                                    "path files than the limit were open)",
                                    path_, std::strerror(errno)));
  }
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode) || static_cast<std::uint64_t>(st.st_dev) != device_ ||
      static_cast<std::uint64_t>(st.st_ino) != inode_) {
    ::close(fd);
    throw DataLossError(fmt::format("target paths file '{}': the name is no longer the file the rig loaded (it was "
                                    "replaced or removed after its descriptor was closed for the limit on open "
                                    "path files)",
                                    path_));
  }
  return fd;
}

void PathFile::SetOpenLimit(int limit) {
  PathFileRegistry& registry = Registry();
  std::lock_guard lock(registry.mutex);
  registry.limit = std::max(0, limit);
  CloseIdle();
}

int PathFile::OpenCount() {
  PathFileRegistry& registry = Registry();
  std::lock_guard lock(registry.mutex);
  return static_cast<int>(registry.open.size());
}

int PathFile::Acquire() const {
  if (!tracked_) return fd_;
  PathFileRegistry& registry = Registry();
  std::lock_guard lock(registry.mutex);
  if (fd_ < 0) {
    fd_ = Reopen();
    registry.open.push_front(this);
    position_ = registry.open.begin();
  } else {
    registry.open.splice(registry.open.begin(), registry.open, position_);
  }
  ++readers_;
  CloseIdle();
  return fd_;
}

void PathFile::Release() const {
  if (!tracked_) return;
  PathFileRegistry& registry = Registry();
  std::lock_guard lock(registry.mutex);
  --readers_;
  CloseIdle();
}

std::shared_ptr<const PathFile> PathFile::Open(const std::string& path, int opened) {
  const int fd = opened >= 0 ? ::fcntl(opened, F_DUPFD_CLOEXEC, 0)
                             : ::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) throw Error(ErrorCode::kInvalidInput, fmt::format("cannot open '{}': {}", path, std::strerror(errno)));
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
    ::close(fd);
    throw Error(ErrorCode::kInvalidInput, fmt::format("'{}' is not a regular file", path));
  }
  // Reads are preads of a regular file: O_NONBLOCK (which only kept the open from waiting) changes nothing.
  std::shared_ptr<PathFile> file(new PathFile(fd, path, static_cast<std::int64_t>(st.st_size)));
  file->Track(static_cast<std::uint64_t>(st.st_dev), static_cast<std::uint64_t>(st.st_ino));
  return file;
}

std::shared_ptr<PathFile> PathFile::Spool(const std::string& directory) {
  int fd = ::open(directory.c_str(), O_TMPFILE | O_RDWR | O_CLOEXEC, 0600);
  if (fd < 0 && (errno == EOPNOTSUPP || errno == EISDIR || errno == EINVAL)) {
    // A file system without O_TMPFILE: a named file, unlinked at once.
    std::string name = directory + "/.springblend-spool-XXXXXX";
    fd = ::mkostemp(name.data(), O_CLOEXEC);
    if (fd >= 0) ::unlink(name.c_str());
  }
  if (fd < 0) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("cannot make a spool file in '{}': {}", directory, std::strerror(errno)));
  }
  return std::shared_ptr<PathFile>(new PathFile(fd, directory + " (spool)", 0));
}

std::int64_t PathFile::Append(const std::string& bytes) {
  std::lock_guard lock(append_);
  const std::int64_t at = size_.load();
  size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t put = ::pwrite(fd_, bytes.data() + done, bytes.size() - done, static_cast<off_t>(at + done));
    if (put < 0 && errno == EINTR) continue;
    if (put <= 0) {
      const int error = put < 0 ? errno : ENOSPC;
      // The bytes written past `at` given back; if that fails they are only overwritten by the next Append (the
      // size stays `at`, and nothing past it is ever read).
      [[maybe_unused]] const int truncated = ::ftruncate(fd_, static_cast<off_t>(at));
      throw Error(ErrorCode::kInternal, fmt::format("target paths file '{}': cannot write {} bytes at {} ({})", path_,
                                                    bytes.size(), at, std::strerror(error)));
    }
    done += static_cast<size_t>(put);
  }
  size_.store(at + static_cast<std::int64_t>(bytes.size()));
  return at;
}

PathFile::~PathFile() {
  if (tracked_) {
    PathFileRegistry& registry = Registry();
    std::lock_guard lock(registry.mutex);
    if (fd_ >= 0) registry.open.erase(position_);
  }
  if (fd_ >= 0) ::close(fd_);
}

void PathFile::Read(std::int64_t offset, size_t n, void* out) const {
  const int fd = Acquire();
  struct Held {
    const PathFile* file;
    ~Held() { file->Release(); }
  } held{this};
  auto* bytes = static_cast<char*>(out);
  size_t done = 0;
  while (done < n) {
    const ssize_t got = ::pread(fd, bytes + done, n - done, static_cast<off_t>(offset + done));
    if (got < 0 && errno == EINTR) continue;
    if (got <= 0) {
      throw DataLossError(
                  fmt::format("target paths file '{}': cannot read {} bytes at {} ({})", path_, n - done,
                              offset + static_cast<std::int64_t>(done),
                              got < 0 ? std::strerror(errno) : "the file was cut short after it was opened"));
    }
    done += static_cast<size_t>(got);
  }
}

PathField PathField::Stored(std::shared_ptr<const PathFile> file, std::int64_t at, Eigen::Index rows, int words,
                            double step) {
  PathField f;
  f.file_ = std::move(file);
  f.at_ = at;
  f.rows_ = rows;
  f.words_ = words;
  f.step_ = step;
  return f;
}

PathField::PathField(const Eigen::MatrixXd& values, int words) {
  const Eigen::Index rows = values.rows();
  rows_ = rows;
  words_ = rows > 0 ? (words < 2 ? 1 : 2) : 0;
  high_.resize(rows, 3);
  const double largest = values.size() > 0 ? values.cwiseAbs().maxCoeff() : 0.0;
  step_ = largest > 0.0 && std::isfinite(largest) ? largest / kHighSteps : 0.0;
  if (step_ == 0.0) {
    high_.setZero();
    words_ = rows > 0 ? 1 : 0;
    return;
  }
  const Eigen::ArrayXXd scaled = values.array() / step_;
  const Eigen::ArrayXXd rounded = scaled.round().min(kHighSteps).max(-kHighSteps);
  high_ = rounded.cast<std::int32_t>().matrix();
  if (words < 2) return;
  low_ = ((scaled - rounded) * kLowScale).round().min(kLowMax).max(-kLowMax).cast<std::int32_t>().matrix();
}

std::int64_t PathField::bytes() const {
  if (empty()) return 0;
  return static_cast<std::int64_t>(sizeof(std::int32_t) * (high_.size() + low_.size()) + sizeof(double));
}

std::int64_t PathField::stored_bytes() const {
  return stored() ? static_cast<std::int64_t>(sizeof(std::int32_t) * 3 * rows_ * words_) : 0;
}

namespace {

// A stored field's words, read into a buffer of the calling thread's (one per word, reused: a frame reads a few
// fields at a time, each used before the next is read).
const std::int32_t* ReadWords(const PathFile& file, std::int64_t at, Eigen::Index rows, int which) {
  thread_local std::vector<std::int32_t> buffers[2];
  std::vector<std::int32_t>& buffer = buffers[which];
  buffer.resize(3 * static_cast<size_t>(rows));
  file.Read(at, sizeof(std::int32_t) * buffer.size(), buffer.data());
  return buffer.data();
}

}  // namespace

const std::int32_t* PathField::HighWords() const {
  return stored() ? ReadWords(*file_, at_, rows_, 0) : high_.data();
}

const std::int32_t* PathField::LowWords() const {
  if (words_ < 2) return nullptr;
  return stored() ? ReadWords(*file_, at_ + static_cast<std::int64_t>(sizeof(std::int32_t) * 3 * rows_), rows_, 1)
                  : low_.data();
}

void PathField::AddTo(double weight, Eigen::MatrixXd* out) const {
  if (empty() || weight == 0.0) return;
  const Eigen::Map<const Words> high(HighWords(), rows_, 3);
  *out += (weight * step_) * high.cast<double>();
  if (words_ == 2) {
    const Eigen::Map<const Words> low(LowWords(), rows_, 3);
    *out += (weight * step_ / kLowScale) * low.cast<double>();
  }
}

Eigen::MatrixXd PathField::Decode() const {
  Eigen::MatrixXd out = Eigen::MatrixXd::Zero(rows(), 3);
  AddTo(1.0, &out);
  return out;
}

void PathField::AppendTo(std::string* out) const {
  out->append(reinterpret_cast<const char*>(&step_), sizeof(step_));
  out->push_back(static_cast<char>(words()));
  const size_t words_size = sizeof(std::int32_t) * 3 * static_cast<size_t>(rows_);
  if (empty()) return;
  out->append(reinterpret_cast<const char*>(HighWords()), words_size);
  if (words_ == 2) out->append(reinterpret_cast<const char*>(LowWords()), words_size);
}

void PathField::MoveTo(const std::shared_ptr<PathFile>& spool) {
  if (empty() || stored()) return;
  std::string bytes;
  bytes.reserve(kHeaderBytes + sizeof(std::int32_t) * static_cast<size_t>(high_.size() + low_.size()));
  AppendTo(&bytes);
  const std::int64_t at = spool->Append(bytes);
  *this = Stored(spool, at + static_cast<std::int64_t>(kHeaderBytes), rows_, words_, step_);
}

void PathField::Load() {
  if (!stored()) return;
  PathField field;
  field.rows_ = rows_;
  field.words_ = words_;
  field.step_ = step_;
  field.high_ = Eigen::Map<const Words>(HighWords(), rows_, 3);
  if (words_ == 2) field.low_ = Eigen::Map<const Words>(LowWords(), rows_, 3);
  *this = std::move(field);
}

bool PathField::ParseHeader(const char* header, double* step, int* words) {
  std::memcpy(step, header, sizeof(double));
  *words = static_cast<std::uint8_t>(header[sizeof(double)]);
  return std::isfinite(*step) && *step >= 0.0 && *words >= 1 && *words <= 2;
}

bool PathField::Parse(const std::string& in, size_t* at, Eigen::Index rows, PathField* field) {
  if (rows <= 0) return false;
  const size_t words_size = sizeof(std::int32_t) * 3 * static_cast<size_t>(rows);
  if (in.size() < *at || in.size() - *at < sizeof(double) + 1) return false;
  double step = 0.0;
  int words = 0;
  const bool valid = ParseHeader(in.data() + *at, &step, &words);
  *at += kHeaderBytes;
  if (!valid) return false;
  if ((in.size() - *at) / words_size < static_cast<size_t>(words)) return false;
  PathField f;
  f.step_ = step;
  f.rows_ = rows;
  f.words_ = words;
  f.high_.resize(rows, 3);
  std::memcpy(f.high_.data(), in.data() + *at, words_size);
  *at += words_size;
  if (words == 2) {
    f.low_.resize(rows, 3);
    std::memcpy(f.low_.data(), in.data() + *at, words_size);
    *at += words_size;
  }
  *field = std::move(f);
  return true;
}

}  // namespace springblend::internal

namespace springblend {

OpenFile::~OpenFile() {
  if (fd_ >= 0) ::close(fd_);
}

void SetOpenPathFileLimit(int limit) { internal::PathFile::SetOpenLimit(limit); }

int OpenPathFiles() { return internal::PathFile::OpenCount(); }

}  // namespace springblend
