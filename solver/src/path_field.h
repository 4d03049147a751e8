// A field of a target path (a sample's correction or its tangent: #vertices by 3) in fixed point.
//
// One word: 32-bit integer steps of the field's largest magnitude / (2^31 - 1), so every coordinate is within
// half a step (2^-32 of the largest magnitude) of its value: the rounding is uniform over the mesh, where a
// float's is relative per coordinate, and 256 times finer for the largest ones at the same size. Two words: a
// second 32-bit integer holds the rest in steps of 2^-32 of the first's (finer than a double's rounding),
// for a sample that one word would put out of balance.
//
// Why not floats: rounding is noise from vertex to vertex, and the forces are the springs' strains, so a
// rounding error counts as itself over an edge's length, however small against the field. On the horse's path
// (bench/paths_bench.cc, one run each): stored as floats, 5 of 17 frames finished locally (141 ms median),
// and a frame exactly at a sample's weight started out of balance at too many vertices; in 32-bit fixed
// point 12 of 17 (7.0 ms median), as with doubles at twice the size (12 of 17, 6.5 ms); 28-bit fixed point
// 12 of 17, 24-bit 1 of 17.
#pragma once

#include <Eigen/Core>
#include <atomic>
#include <cstdint>
#include <list>
#include <memory>
#include <mutex>
#include <string>

namespace springblend::internal {

// A read-only file that holds fields' words (a cache file the paths were saved to), read with pread as frames
// need them, so a rig's resident memory does not grow with its paths. The file must not change while it is open
// (the server's cache replaces files by renaming, so an open one keeps its contents).
//
// A file with a name (not a spool) is one of the process's open path files, of which at most
// SetOpenPathFileLimit are kept open: past it, the least recently read whose reads are over is closed, and
// opened again by its name when it is next read, only if the name is still the same file (device and inode;
// opened without following links or blocking, a regular file), else the read fails with DataLossError.
class PathFile {
 public:
  // Throws Error(kInvalidInput) naming the file when it cannot be opened or is not a regular file. With
  // `opened`, a duplicate of that descriptor is read (`path` only names it); without, `path` is opened without
  // blocking (a FIFO there is refused, never waited on).
  static std::shared_ptr<const PathFile> Open(const std::string& path, int opened = -1);
  // A new file without a name in `directory` (O_TMPFILE, or a file unlinked at once where the file system has
  // none), empty, for a build to leave its paths' words in as each is solved (Append): its disk space is given
  // back when the last field that reads it is gone. Throws Error(kInvalidInput) naming the directory when it
  // cannot be made.
  static std::shared_ptr<PathFile> Spool(const std::string& directory);
  ~PathFile();
  PathFile(const PathFile&) = delete;
  PathFile& operator=(const PathFile&) = delete;

  const std::string& path() const { return path_; }
  std::int64_t size() const { return size_.load(); }
  // n bytes at `offset` into out; throws DataLossError (kInternal) naming the file and the offset when they cannot
  // be read (a file cut short after it was opened), or when a file closed for the limit on open files cannot be
  // opened again as the same file (removed, or another renamed over its name, since).
  void Read(std::int64_t offset, size_t n, void* out) const;
  // Writes `bytes` at the end of a spool (thread-safe) and returns their offset; throws Error(kInternal) naming
  // the directory when they cannot all be written (a full disk), the file's size then unchanged.
  std::int64_t Append(const std::string& bytes);
  // springblend::SetOpenPathFileLimit and OpenPathFiles (open_files.h).
  static void SetOpenLimit(int limit);
  static int OpenCount();

 private:
  PathFile(int fd, std::string path, std::int64_t size) : fd_(fd), path_(std::move(path)), size_(size) {}
  // A named file joins the open path files (and may close another's descriptor).
  void Track(std::uint64_t device, std::uint64_t inode);
  // The descriptor, open (opened again when the limit closed it), held open until Release.
  int Acquire() const;
  void Release() const;
  int Reopen() const;  // throws DataLossError when the name is no longer this file
  // Closes the least recently read files no read holds until at most the limit are open; the registry's lock held.
  static void CloseIdle();

  mutable int fd_ = -1;  // a tracked file's is guarded by the registry's lock (closed and reopened)
  std::string path_;
  std::atomic<std::int64_t> size_{0};
  std::mutex append_;
  bool tracked_ = false;  // a named file, closed and reopened as the limit needs; a spool stays open
  std::uint64_t device_ = 0, inode_ = 0;
  // The registry's lock guards these: reads in progress, and its place among the open files when open.
  mutable int readers_ = 0;
  mutable std::list<const PathFile*>::iterator position_;
};

class PathField {
 public:
  using Words = Eigen::Matrix<std::int32_t, Eigen::Dynamic, 3>;

  PathField() = default;
  // `values` #vertices by 3 (finite); `words` 1 or 2.
  explicit PathField(const Eigen::MatrixXd& values, int words = 1);

  // A field whose words are in `file` at `at` (as AppendTo wrote them after the step and the word count), read
  // when it is used.
  static PathField Stored(std::shared_ptr<const PathFile> file, std::int64_t at, Eigen::Index rows, int words,
                          double step);

  bool empty() const { return rows_ == 0; }
  Eigen::Index rows() const { return rows_; }
  int words() const { return words_; }
  double step() const { return step_; }  // value of the first word's unit
  bool stored() const { return file_ != nullptr; }
  std::int64_t bytes() const;         // memory it holds (a stored field: its step only); 0 when empty
  std::int64_t stored_bytes() const;  // its words in a file; 0 when held in memory

  // out += weight * field (out #vertices by 3).
  void AddTo(double weight, Eigen::MatrixXd* out) const;
  Eigen::MatrixXd Decode() const;

  // Little-endian bytes: step (double), words (uint8), then the words, column-major.
  void AppendTo(std::string* out) const;
  // A field held in memory writes its words to `spool` (PathFile::Append) and from then on reads them there
  // (stored()); one already stored, or empty, is left as it is. Throws as Append does, the field then unchanged.
  void MoveTo(const std::shared_ptr<PathFile>& spool);
  // The reverse: a stored field reads its words into memory and lets its file go (a spool whose paths could not
  // be kept in a cache file gives its disk space back once no field reads it). Throws as Read does.
  void Load();
  // Reads one field of `rows` rows at *at; false (and *at unspecified) when the bytes are not one.
  static bool Parse(const std::string& in, size_t* at, Eigen::Index rows, PathField* field);
  // The step and word count that begin a field (AppendTo's first 9 bytes); false when they are not valid.
  static bool ParseHeader(const char* header, double* step, int* words);
  static constexpr size_t kHeaderBytes = sizeof(double) + 1;

 private:
  // The words, from memory or read from the file into a buffer of this thread's.
  const std::int32_t* HighWords() const;
  const std::int32_t* LowWords() const;

  Words high_;  // empty for a stored field
  Words low_;   // empty for one word or a stored field
  double step_ = 0.0;
  Eigen::Index rows_ = 0;
  int words_ = 0;
  std::shared_ptr<const PathFile> file_;  // set for a stored field
  std::int64_t at_ = 0;                   // its first word's offset in file_
};

}  // namespace springblend::internal
