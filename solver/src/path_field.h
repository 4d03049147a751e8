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
#include <cstdint>
#include <string>

namespace springblend::internal {

class PathField {
 public:
  using Words = Eigen::Matrix<std::int32_t, Eigen::Dynamic, 3>;

  PathField() = default;
  // `values` #vertices by 3 (finite); `words` 1 or 2.
  explicit PathField(const Eigen::MatrixXd& values, int words = 1);

  bool empty() const { return high_.size() == 0; }
  Eigen::Index rows() const { return high_.rows(); }
  int words() const { return empty() ? 0 : low_.size() > 0 ? 2 : 1; }
  double step() const { return step_; }  // value of the first word's unit
  std::int64_t bytes() const;  // 0 when empty

  // out += weight * field (out #vertices by 3).
  void AddTo(double weight, Eigen::MatrixXd* out) const;
  Eigen::MatrixXd Decode() const;

  // Little-endian bytes: step (double), words (uint8), then the words, column-major.
  void AppendTo(std::string* out) const;
  // Reads one field of `rows` rows at *at; false (and *at unspecified) when the bytes are not one.
  static bool Parse(const std::string& in, size_t* at, Eigen::Index rows, PathField* field);

 private:
  Words high_;
  Words low_;  // empty for one word
  double step_ = 0.0;
};

}  // namespace springblend::internal
