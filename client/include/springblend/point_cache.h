// PC2 point caches: every frame's vertex positions in one binary file, which Blender's Mesh Cache modifier,
// 3ds Max, Maya and Houdini play back. Layout, little-endian: the 12-byte signature "POINTCACHE2\0", int32
// version (1), int32 number of points, float32 start frame, float32 sample rate (frames per sample), int32
// number of samples, then float32 x y z per point per sample. springblend writes frame i (0-based) of a solve
// as sample i, with start frame 1 unless told otherwise.
#pragma once

#include <cstdint>
#include <fstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "springblend/geometry.h"

namespace springblend {

// A file that cannot be written or read, or does not hold a PC2 cache; the message names the path.
class PointCacheError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Writes samples as they come (a Solve streams its frames in order). The cache is written beside `path`
// under a temporary name and renamed onto it by Close(), so the path holds a whole cache or its earlier
// content: a failed or abandoned write (destroyed before Close) leaves nothing half-written behind.
class PointCacheWriter {
 public:
  PointCacheWriter(std::string path, int num_points, float start_frame = 1.0f, float sample_rate = 1.0f);
  ~PointCacheWriter();
  PointCacheWriter(const PointCacheWriter&) = delete;
  PointCacheWriter& operator=(const PointCacheWriter&) = delete;

  // Appends one sample of num_points positions (rounded to float32).
  void Add(const Points& positions);
  // Appends one sample given as packed float32 little-endian x y z (a SolvedFrame's positions, as sent).
  void AddPacked(const std::string& float32_xyz);
  // Writes the sample count into the header and puts the file in place. Throws PointCacheError.
  void Close();

  int samples() const { return samples_; }
  const std::string& path() const { return path_; }

 private:
  void WriteBytes(const char* data, std::size_t size);
  void CheckFinite(const float* values, std::size_t count) const;

  std::string path_, partial_path_;
  int num_points_;
  int samples_ = 0;
  bool closed_ = false;
  int fd_ = -1;  // the temporary, opened O_CREAT | O_EXCL | O_NOFOLLOW
};

struct PointCache {
  float start_frame = 1.0f;
  float sample_rate = 1.0f;
  std::vector<Points> samples;  // each #points by 3
};

// Reads a whole PC2 file; throws PointCacheError naming the path and what is wrong.
PointCache ReadPointCache(const std::string& path);

// True when a path names a PC2 file (ends in ".pc2", any case).
bool IsPointCachePath(const std::string& path);

}  // namespace springblend
