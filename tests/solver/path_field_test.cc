// PathField: a target path's fields in fixed point. One word rounds every coordinate to within 2^-32 of the
// field's largest magnitude (uniformly, where a float rounds relative to each coordinate); two words to
// within a double's rounding of it; the bytes round-trip exactly and malformed ones are refused.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <random>

#include "path_field.h"

namespace springblend::internal {
namespace {

Eigen::MatrixXd RandomField(int rows, double scale, unsigned seed) {
  std::mt19937 random(seed);
  std::uniform_real_distribution<double> uniform(-1.0, 1.0);
  Eigen::MatrixXd m(rows, 3);
  for (Eigen::Index i = 0; i < m.size(); ++i) m.data()[i] = scale * uniform(random) * std::pow(10.0, 3 * uniform(random));
  return m;
}

TEST(PathField, OneWordRoundsUniformlyWithinTwoToTheMinus32OfTheLargest) {
  const Eigen::MatrixXd m = RandomField(1000, 0.37, 1);
  const double largest = m.cwiseAbs().maxCoeff();
  const PathField field(m);
  EXPECT_EQ(field.words(), 1);
  EXPECT_EQ(field.rows(), 1000);
  const double error = (field.Decode() - m).cwiseAbs().maxCoeff();
  EXPECT_LE(error, 1.01 * largest * std::ldexp(1.0, -32));
  EXPECT_GT(error, 0.0);
  // Finer than floats where it matters: the largest coordinates' float rounding is 2^-24 of them.
  const double float_error = (m.cast<float>().cast<double>() - m).cwiseAbs().maxCoeff();
  EXPECT_LT(error * 64, float_error);
  EXPECT_EQ(field.bytes(), static_cast<std::int64_t>(4 * m.size() + 8));
}

TEST(PathField, TwoWordsKeepADoublesPrecision) {
  const Eigen::MatrixXd m = RandomField(500, 3.0, 2);
  const double largest = m.cwiseAbs().maxCoeff();
  const PathField field(m, 2);
  EXPECT_EQ(field.words(), 2);
  EXPECT_LE((field.Decode() - m).cwiseAbs().maxCoeff(), 4e-16 * largest);
  EXPECT_EQ(field.bytes(), static_cast<std::int64_t>(8 * m.size() + 8));
}

TEST(PathField, AddToAddsTheWeightedField) {
  const Eigen::MatrixXd m = RandomField(50, 1.0, 3);
  const PathField field(m, 2);
  Eigen::MatrixXd out = Eigen::MatrixXd::Ones(50, 3);
  field.AddTo(-0.5, &out);
  EXPECT_LE((out - (Eigen::MatrixXd::Ones(50, 3) - 0.5 * m)).cwiseAbs().maxCoeff(), 1e-15 * m.cwiseAbs().maxCoeff());
}

TEST(PathField, AZeroFieldIsExact) {
  const PathField field(Eigen::MatrixXd::Zero(10, 3));
  EXPECT_EQ(field.step(), 0.0);
  EXPECT_TRUE(field.Decode().isZero(0.0));
  EXPECT_TRUE(PathField().empty());
}

TEST(PathField, BytesRoundTripExactlyAndMalformedOnesAreRefused) {
  const Eigen::MatrixXd m = RandomField(20, 0.01, 4);
  for (int words : {1, 2}) {
    const PathField field(m, words);
    std::string bytes = "xy";
    field.AppendTo(&bytes);
    size_t at = 2;
    PathField back;
    ASSERT_TRUE(PathField::Parse(bytes, &at, 20, &back));
    EXPECT_EQ(at, bytes.size());
    EXPECT_EQ(back.words(), words);
    EXPECT_TRUE(back.Decode() == field.Decode());
    // Truncated, another row count's worth, a bad word count, a negative step.
    at = 2;
    EXPECT_FALSE(PathField::Parse(bytes.substr(0, bytes.size() - 1), &at, 20, &back));
    at = 2;
    EXPECT_FALSE(PathField::Parse(bytes, &at, 21 * words, &back));
    std::string bad = bytes;
    bad[2 + 8] = 3;
    at = 2;
    EXPECT_FALSE(PathField::Parse(bad, &at, 20, &back));
    bad = bytes;
    const double negative = -1.0;
    std::memcpy(bad.data() + 2, &negative, sizeof(negative));
    at = 2;
    EXPECT_FALSE(PathField::Parse(bad, &at, 20, &back));
  }
}

}  // namespace
}  // namespace springblend::internal
