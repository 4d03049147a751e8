// The start predictor without a rig: linear blend, warm start, and the polynomial through past frames.
#include "predictor.h"

#include <gtest/gtest.h>

namespace springblend::internal {
namespace {

// Positions that move along a quadratic path in the weight w: p(w) = base + w d1 + w^2 d2.
Points Path(double w) {
  Points p(4, 3);
  for (int v = 0; v < 4; ++v) {
    p.row(v) << v + w + 0.5 * w * w, 2.0 * w - w * w, 0.1 * v * w * w;
  }
  return p;
}

Eigen::VectorXd Stack(const Points& p) {
  Eigen::VectorXd x(3 * p.rows());
  for (Eigen::Index v = 0; v < p.rows(); ++v) x.segment<3>(3 * v) = p.row(v).transpose();
  return x;
}

const auto kNoEnergy = [](const Eigen::VectorXd&) { return 0.0; };

TEST(Predictor, WithoutHistoryStartsFromTheLinearBlend) {
  Predictor predictor;
  const Points linear = Path(0.3);
  Eigen::VectorXd x;
  predictor.Predict(linear, std::nullopt, Eigen::Vector3d::Zero(), {0.3}, {}, true, kNoEnergy, &x);
  EXPECT_EQ(x, Stack(linear));
}

TEST(Predictor, AWarmStartIsUsedWithTheFramesHeldVertices) {
  Predictor predictor;
  predictor.SetStart(Path(0.5));
  Eigen::VectorXd x;
  const Eigen::Vector3d pin(9.0, 9.0, 9.0);
  predictor.Predict(Path(0.0), std::nullopt, Eigen::Vector3d::Zero(), {0.6}, {{2, pin}}, true, kNoEnergy, &x);
  Eigen::VectorXd expected = Stack(Path(0.5));
  expected.segment<3>(6) = pin;
  EXPECT_EQ(x, expected);
}

TEST(Predictor, ThreeFramesOnALineOfWeightsReproduceAQuadraticPathExactly) {
  Predictor predictor;
  for (double w : {0.1, 0.2, 0.3}) predictor.Add(Path(w), std::nullopt, {w}, true);
  Eigen::VectorXd x;
  predictor.Predict(Path(0.0), std::nullopt, Eigen::Vector3d::Zero(), {0.4}, {}, true, kNoEnergy, &x);
  EXPECT_LT((x - Stack(Path(0.4))).lpNorm<Eigen::Infinity>(), 1e-12);
}

TEST(Predictor, FramesOffTheLineOrUnconvergedAreNoNodes) {
  Predictor predictor;
  predictor.Add(Path(0.1), std::nullopt, {0.1, 0.0}, true);
  predictor.Add(Path(0.2), std::nullopt, {0.2, 0.0}, true);
  predictor.Add(Path(0.3), std::nullopt, {0.3, 0.0}, false);  // not converged: a warm start only
  Eigen::VectorXd x;
  predictor.Predict(Path(0.0), std::nullopt, Eigen::Vector3d::Zero(), {0.4, 0.0}, {}, true, kNoEnergy, &x);
  EXPECT_EQ(x, Stack(Path(0.3)));
  Predictor turning;
  for (double w : {0.1, 0.2, 0.3}) turning.Add(Path(w), std::nullopt, {w, 0.0}, true);
  turning.Predict(Path(0.0), std::nullopt, Eigen::Vector3d::Zero(), {0.3, 0.5}, {}, true, kNoEnergy, &x);
  EXPECT_EQ(x, Stack(Path(0.3)));  // turning off the line: the previous solution
}

TEST(Predictor, TheLowestEnergyOrderWins) {
  Predictor predictor;
  for (double w : {0.1, 0.2, 0.3}) predictor.Add(Path(w), std::nullopt, {w}, true);
  const Eigen::VectorXd previous = Stack(Path(0.3));
  // An energy that prefers the zeroth order (the previous solution) over any extrapolation.
  const auto energy = [&](const Eigen::VectorXd& x) { return (x - previous).squaredNorm(); };
  Eigen::VectorXd x;
  predictor.Predict(Path(0.0), std::nullopt, Eigen::Vector3d::Zero(), {0.4}, {}, true, energy, &x);
  EXPECT_EQ(x, previous);
}

TEST(Predictor, AnchoredFramesAreExtrapolatedInTheAnchorsFrame) {
  // The same path seen through a rigid motion that changes per frame is extrapolated in the local frame.
  const Eigen::Vector3d c(1.0, 2.0, 3.0);
  const auto motion_at = [](double w) {
    AnchorMotion m;
    m.rotation = Eigen::Quaterniond(Eigen::AngleAxisd(w, Eigen::Vector3d::UnitZ()));
    m.offset = Eigen::Vector3d(w, 0.0, 0.0);
    return m;
  };
  const auto world = [&](double w) {
    Points p = Path(w);
    const AnchorMotion m = motion_at(w);
    for (Eigen::Index v = 0; v < p.rows(); ++v) p.row(v) = m.Apply(p.row(v).transpose(), c).transpose();
    return p;
  };
  Predictor predictor;
  for (double w : {0.1, 0.2, 0.3}) predictor.Add(world(w), motion_at(w), {w}, true);
  Eigen::VectorXd x;
  predictor.Predict(Path(0.0), motion_at(0.4), c, {0.4}, {}, true, kNoEnergy, &x);
  EXPECT_LT((x - Stack(world(0.4))).lpNorm<Eigen::Infinity>(), 1e-12);
}

}  // namespace
}  // namespace springblend::internal
