#include "path_field.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

namespace springblend::internal {
namespace {

constexpr double kHighSteps = 2147483647.0;         // 2^31 - 1: the largest magnitude's steps
constexpr double kLowScale = 4294967296.0;          // 2^32 low steps per high step
constexpr double kLowMax = 2147483647.0;

}  // namespace

PathField::PathField(const Eigen::MatrixXd& values, int words) {
  const Eigen::Index rows = values.rows();
  high_.resize(rows, 3);
  const double largest = values.size() > 0 ? values.cwiseAbs().maxCoeff() : 0.0;
  step_ = largest > 0.0 && std::isfinite(largest) ? largest / kHighSteps : 0.0;
  if (step_ == 0.0) {
    high_.setZero();
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

void PathField::AddTo(double weight, Eigen::MatrixXd* out) const {
  if (empty() || weight == 0.0) return;
  *out += (weight * step_) * high_.cast<double>();
  if (low_.size() > 0) *out += (weight * step_ / kLowScale) * low_.cast<double>();
}

Eigen::MatrixXd PathField::Decode() const {
  Eigen::MatrixXd out = Eigen::MatrixXd::Zero(rows(), 3);
  AddTo(1.0, &out);
  return out;
}

void PathField::AppendTo(std::string* out) const {
  out->append(reinterpret_cast<const char*>(&step_), sizeof(step_));
  out->push_back(static_cast<char>(words()));
  out->append(reinterpret_cast<const char*>(high_.data()), sizeof(std::int32_t) * static_cast<size_t>(high_.size()));
  out->append(reinterpret_cast<const char*>(low_.data()), sizeof(std::int32_t) * static_cast<size_t>(low_.size()));
}

bool PathField::Parse(const std::string& in, size_t* at, Eigen::Index rows, PathField* field) {
  if (rows <= 0) return false;
  const size_t words_size = sizeof(std::int32_t) * 3 * static_cast<size_t>(rows);
  if (in.size() < *at || in.size() - *at < sizeof(double) + 1) return false;
  double step = 0.0;
  std::memcpy(&step, in.data() + *at, sizeof(step));
  const auto words = static_cast<std::uint8_t>(in[*at + sizeof(step)]);
  *at += sizeof(step) + 1;
  if (!(std::isfinite(step) && step >= 0.0) || words < 1 || words > 2) return false;
  if ((in.size() - *at) / words_size < words) return false;
  PathField f;
  f.step_ = step;
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
