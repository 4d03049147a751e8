// The PC2 writer and reader of the client library: the header byte for byte, samples read back, packed
// float32 frames as the server sends them, and the refusals.
#include "springblend/point_cache.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>

#include "test_util.h"

namespace springblend {
namespace {

using ::testing::HasSubstr;
using testing::TempDir;

std::string ReadBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

template <typename T>
T At(const std::string& bytes, std::size_t offset) {
  T value;
  std::memcpy(&value, bytes.data() + offset, sizeof value);  // the tests run on little-endian hosts
  return value;
}

Points Sample(int points, double shift) {
  Points p(points, 3);
  for (int i = 0; i < points; ++i) p.row(i) << i + shift, -0.5 * i + shift, 0.25 * i * i - shift;
  return p;
}

TEST(PointCache, HeaderIsTheFormatsLayoutByteForByte) {
  TempDir dir;
  PointCacheWriter writer(dir.File("a.pc2"), 4, 1.0f, 1.0f);
  writer.Add(Sample(4, 0.0));
  writer.Add(Sample(4, 1.0));
  writer.Add(Sample(4, 2.0));
  writer.Close();
  const std::string bytes = ReadBytes(dir.File("a.pc2"));
  ASSERT_EQ(bytes.size(), 32u + 3 * 4 * 12);
  EXPECT_EQ(std::memcmp(bytes.data(), "POINTCACHE2\0", 12), 0);
  EXPECT_EQ(At<std::int32_t>(bytes, 12), 1);  // version
  EXPECT_EQ(At<std::int32_t>(bytes, 16), 4);  // points
  EXPECT_EQ(At<float>(bytes, 20), 1.0f);      // start frame
  EXPECT_EQ(At<float>(bytes, 24), 1.0f);      // sample rate
  EXPECT_EQ(At<std::int32_t>(bytes, 28), 3);  // samples
  // Sample 1, point 2: x y z as float32 right after sample 0.
  const std::size_t offset = 32 + (1 * 4 + 2) * 12;
  EXPECT_EQ(At<float>(bytes, offset), 3.0f);
  EXPECT_EQ(At<float>(bytes, offset + 4), 0.0f);
  EXPECT_EQ(At<float>(bytes, offset + 8), 0.0f);
}

TEST(PointCache, ReadsBackWhatWasWrittenAtFloatPrecision) {
  TempDir dir;
  const std::string path = dir.File("b.pc2");
  {
    PointCacheWriter writer(path, 5, 10.0f, 0.5f);
    for (int s = 0; s < 7; ++s) writer.Add(Sample(5, 0.1 * s));
    writer.Close();
    EXPECT_EQ(writer.samples(), 7);
  }
  const PointCache cache = ReadPointCache(path);
  EXPECT_EQ(cache.start_frame, 10.0f);
  EXPECT_EQ(cache.sample_rate, 0.5f);
  ASSERT_EQ(cache.samples.size(), 7u);
  for (int s = 0; s < 7; ++s) {
    EXPECT_EQ(cache.samples[s], Sample(5, 0.1 * s).cast<float>().cast<double>()) << "sample " << s;
  }
}

TEST(PointCache, PackedFloat32FramesGoInAsSent) {
  TempDir dir;
  const Points p = Sample(3, 0.3);
  std::string packed(3 * 12, '\0');
  for (int i = 0; i < 3; ++i) {
    for (int c = 0; c < 3; ++c) {
      const float v = static_cast<float>(p(i, c));
      std::memcpy(packed.data() + (i * 3 + c) * 4, &v, 4);
    }
  }
  PointCacheWriter writer(dir.File("c.pc2"), 3);
  writer.AddPacked(packed);
  writer.Add(p);
  writer.Close();
  const PointCache cache = ReadPointCache(dir.File("c.pc2"));
  ASSERT_EQ(cache.samples.size(), 2u);
  EXPECT_EQ(cache.samples[0], cache.samples[1]);
  EXPECT_THROW(writer.Add(p), PointCacheError);  // closed
}

TEST(PointCache, NothingAppearsUntilCloseAndAnAbandonedWriteLeavesNothing) {
  TempDir dir;
  const std::string path = dir.File("d.pc2");
  {
    PointCacheWriter writer(path, 2);
    writer.Add(Sample(2, 0));
    EXPECT_FALSE(std::filesystem::exists(path));
  }
  EXPECT_FALSE(std::filesystem::exists(path));
  EXPECT_TRUE(std::filesystem::is_empty(dir.path()));
}

TEST(PointCache, RefusesWrongSizesBadPathsAndBadFiles) {
  TempDir dir;
  PointCacheWriter writer(dir.File("e.pc2"), 4);
  EXPECT_THROW(writer.Add(Sample(3, 0)), PointCacheError);
  EXPECT_THROW(writer.AddPacked(std::string(5, '\0')), PointCacheError);
  try {
    PointCacheWriter nowhere(dir.File("missing/dir/f.pc2"), 4);
    ADD_FAILURE() << "a writer in a missing directory";
  } catch (const PointCacheError& e) {
    EXPECT_THAT(e.what(), HasSubstr("missing/dir/f.pc2"));
  }
  dir.Write("g.pc2", "not a cache at all, just some text");
  try {
    ReadPointCache(dir.File("g.pc2"));
    ADD_FAILURE() << "read a text file";
  } catch (const PointCacheError& e) {
    EXPECT_THAT(e.what(), HasSubstr("POINTCACHE2"));
  }
  {
    PointCacheWriter two(dir.File("h.pc2"), 2);
    two.Add(Sample(2, 0));
    two.Close();
  }
  std::filesystem::resize_file(dir.File("h.pc2"), 40);
  EXPECT_THROW(ReadPointCache(dir.File("h.pc2")), PointCacheError);
}

TEST(PointCache, KnowsItsPaths) {
  EXPECT_TRUE(IsPointCachePath("out/shot.pc2"));
  EXPECT_TRUE(IsPointCachePath("SHOT.PC2"));
  EXPECT_FALSE(IsPointCachePath("out/frames"));
  EXPECT_FALSE(IsPointCachePath("pc2"));
  EXPECT_FALSE(IsPointCachePath("frame.obj"));
}

// A planted NAME.pc2.partial -> victim must not get the victim overwritten: the temporary is created afresh
// (O_CREAT | O_EXCL | O_NOFOLLOW), a link in its place refused, a stale regular partial replaced.
TEST(PointCache, APlantedPartialLinkIsNotFollowed) {
  TempDir dir;
  const std::string victim = dir.Write("victim.txt", "keep me");
  const std::string path = dir.File("link.pc2");
  std::filesystem::create_symlink(victim, path + ".partial");
  try {
    PointCacheWriter writer(path, 3);
    writer.Add(Sample(3, 0.0));
    writer.Close();
    ADD_FAILURE() << "wrote through the link";
  } catch (const PointCacheError& e) {
    EXPECT_THAT(e.what(), HasSubstr("link.pc2.partial"));
  }
  EXPECT_EQ(ReadBytes(victim), "keep me");
  EXPECT_TRUE(std::filesystem::is_symlink(path + ".partial")) << "the link is left for its owner to see";
  EXPECT_FALSE(std::filesystem::exists(path));
  // A dangling link, too.
  const std::string dangling = dir.File("dangling.pc2");
  std::filesystem::create_symlink(dir.File("nowhere.txt"), dangling + ".partial");
  EXPECT_THROW(PointCacheWriter(dangling, 3), PointCacheError);
  EXPECT_FALSE(std::filesystem::exists(dir.File("nowhere.txt")));
  // A stale regular partial (a run killed mid-write) is replaced.
  const std::string stale = dir.File("stale.pc2");
  dir.Write("stale.pc2.partial", "half a cache");
  {
    PointCacheWriter writer(stale, 3);
    writer.Add(Sample(3, 0.0));
    writer.Close();
  }
  EXPECT_EQ(ReadPointCache(stale).samples.size(), 1u);
  EXPECT_FALSE(std::filesystem::exists(stale + ".partial"));
}

// Samples are float32: a coordinate beyond it (inf once rounded) is refused, not written into the cache.
TEST(PointCache, RefusesSamplesThatAreNotFiniteAsFloat32) {
  TempDir dir;
  const std::string path = dir.File("inf.pc2");
  PointCacheWriter writer(path, 3);
  Points huge = Sample(3, 0.0);
  huge(1, 2) = 1e300;
  EXPECT_THROW(writer.Add(huge), PointCacheError);
  std::string packed(36, '\0');
  const float inf = std::numeric_limits<float>::infinity();
  std::memcpy(packed.data() + 8, &inf, 4);
  try {
    writer.AddPacked(packed);
    ADD_FAILURE() << "an infinite sample was written";
  } catch (const PointCacheError& e) {
    EXPECT_THAT(e.what(), HasSubstr("non-finite"));
  }
  EXPECT_EQ(writer.samples(), 0);
}

}  // namespace
}  // namespace springblend
