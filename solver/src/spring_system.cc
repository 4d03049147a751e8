#include "spring_system.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

namespace springblend::internal {

namespace {
constexpr size_t kGrain = 2048;
}  // namespace

SpringSystem::SpringSystem(const SpringTopology& topology) : topology_(topology) {
  const size_t m = static_cast<size_t>(topology.springs());
  const Eigen::Index n = topology.vertices;
  spring_hessian_.resize(6 * m);
  spring_force_.resize(3 * m);
  spring_product_.resize(3 * m);
  stiffness_.resize(m);
  force_.resize(3 * n);
  reaction_.resize(3 * n);
}

void SpringSystem::SetRestLengths(std::vector<double> rest_lengths, std::span<const SpringKind> kinds,
                                  const std::array<double, 3>& kind_stiffness, double stiffness_floor) {
  rest_length_ = std::move(rest_lengths);
  const size_t m = rest_length_.size();
  stiffness_.resize(m);
  for (size_t q = 0; q < m; ++q) {
    stiffness_[q] = kind_stiffness[static_cast<int>(kinds[q])] / std::max(rest_length_[q], stiffness_floor);
  }
}

double SpringSystem::Energy(const Eigen::VectorXd& x) const {
  const int* a = topology_.a.data();
  const int* b = topology_.b.data();
  return tbb::parallel_deterministic_reduce(
      tbb::blocked_range<int>(0, topology_.springs(), kGrain), 0.0,
      [&](const tbb::blocked_range<int>& range, double sum) {
        for (int q = range.begin(); q != range.end(); ++q) {
          const double l = (x.segment<3>(3 * a[q]) - x.segment<3>(3 * b[q])).norm();
          const double stretch = l - rest_length_[q];
          sum += 0.5 * stiffness_[q] * stretch * stretch;
        }
        return sum;
      },
      [](double l, double r) { return l + r; });
}

double SpringSystem::Evaluate(const Eigen::VectorXd& x, const std::vector<char>& held, const Curvature& curvature,
                              bool blocks) {
  return Run(x, held, curvature, 0.0, nullptr, blocks);
}

double SpringSystem::Assemble(const Eigen::VectorXd& x, const std::vector<char>& held, const Curvature& curvature,
                              double diagonal_shift, std::vector<double>* values) {
  return Run(x, held, curvature, diagonal_shift, values, true);
}

double SpringSystem::Run(const Eigen::VectorXd& x, const std::vector<char>& held, const Curvature& curvature,
                         double shift, std::vector<double>* values_out, bool blocks) {
  const bool hessian = values_out != nullptr;
  const int m = topology_.springs();
  const int n = topology_.vertices;
  const int* a = topology_.a.data();
  const int* b = topology_.b.data();
  const double tiny = tiny_length_;
  const HessianPattern& pattern = *topology_.pattern;
  const char* fixed = held.data();
  double* values = hessian ? values_out->data() : nullptr;
  const double negative_scale = curvature.negative_scale;
  const bool absolute = curvature.absolute;

  tbb::parallel_for(tbb::blocked_range<int>(0, m, kGrain), [&](const tbb::blocked_range<int>& range) {
    for (int q = range.begin(); q != range.end(); ++q) {
      const Eigen::Vector3d d = x.segment<3>(3 * a[q]) - x.segment<3>(3 * b[q]);
      const double l = d.norm();
      const double k = stiffness_[q];
      double* hq = &spring_hessian_[6 * static_cast<size_t>(q)];
      double* fq = &spring_force_[3 * static_cast<size_t>(q)];
      Eigen::Matrix3d h;
      if (!blocks) {
        if (l <= tiny) {
          fq[0] = fq[1] = fq[2] = 0.0;
        } else {
          const double scale = -k * (l - rest_length_[q]) / l;
          fq[0] = scale * d[0];
          fq[1] = scale * d[1];
          fq[2] = scale * d[2];
        }
        continue;
      }
      if (l <= tiny) {
        // Coincident endpoints: no direction to push along; a plain spring-like stiffness keeps H SPD.
        fq[0] = fq[1] = fq[2] = 0.0;
        h = k * Eigen::Matrix3d::Identity();
      } else {
        const Eigen::Vector3d u = d / l;
        const double stretch = l - rest_length_[q];
        fq[0] = -k * stretch * u[0];
        fq[1] = -k * stretch * u[1];
        fq[2] = -k * stretch * u[2];
        // H_q = k [u u^T + s (I - u u^T)], s = 1 - r̄/l; projected Newton clamps s at zero.
        double s = 1.0 - rest_length_[q] / l;
        if (s < 0.0) s = absolute ? -s : s * negative_scale;
        h = k * ((1.0 - s) * (u * u.transpose()) + s * Eigen::Matrix3d::Identity());
      }
      hq[0] = h(0, 0), hq[1] = h(0, 1), hq[2] = h(0, 2), hq[3] = h(1, 1), hq[4] = h(1, 2), hq[5] = h(2, 2);
      if (hessian) {
        const auto& slots = pattern.spring_slots[q];
        for (int ci = 0; ci < 3; ++ci) {
          for (int cj = 0; cj < 3; ++cj) {
            const bool pinned = fixed[3 * a[q] + ci] || fixed[3 * b[q] + cj];
            values[slots[ci * 3 + cj]] = pinned ? 0.0 : -h(ci, cj);
          }
        }
      }
    }
  });

  const int* offsets = topology_.vertex_spring_offsets.data();
  const int* incident = topology_.vertex_springs.data();
  return tbb::parallel_deterministic_reduce(
      tbb::blocked_range<int>(0, n, kGrain), 0.0,
      [&](const tbb::blocked_range<int>& range, double residual) {
        for (int v = range.begin(); v != range.end(); ++v) {
          double h[6] = {0, 0, 0, 0, 0, 0};
          double f[3] = {0, 0, 0};
          for (int e = offsets[v]; e < offsets[v + 1]; ++e) {
            const int q = incident[e];
            const double sign = a[q] == v ? 1.0 : -1.0;
            const double* fq = &spring_force_[3 * static_cast<size_t>(q)];
            if (hessian) {
              const double* hq = &spring_hessian_[6 * static_cast<size_t>(q)];
              for (int i = 0; i < 6; ++i) h[i] += hq[i];
            }
            for (int i = 0; i < 3; ++i) f[i] += sign * fq[i];
          }
          for (int c = 0; c < 3; ++c) {
            const bool pinned = fixed[3 * v + c];
            reaction_[3 * v + c] = f[c];
            force_[3 * v + c] = pinned ? 0.0 : f[c];
            residual = std::max(residual, std::abs(force_[3 * v + c]));
          }
          if (hessian) {
            const auto& slots = pattern.vertex_slots[v];
            static constexpr int kRow[6] = {0, 0, 0, 1, 1, 2};
            static constexpr int kCol[6] = {0, 1, 2, 1, 2, 2};
            for (int i = 0; i < 6; ++i) {
              const bool pin_row = fixed[3 * v + kRow[i]];
              const bool pin_col = fixed[3 * v + kCol[i]];
              double value;
              if (kRow[i] == kCol[i]) {
                value = pin_row ? 1.0 : h[i] + shift;
              } else {
                value = (pin_row || pin_col) ? 0.0 : h[i];
              }
              values[slots[i]] = value;
            }
          }
        }
        return residual;
      },
      [](double l, double r) { return std::max(l, r); });
}

void SpringSystem::HessianProduct(const Eigen::VectorXd& v, const std::vector<char>& held, double shift,
                                  Eigen::VectorXd* product) {
  // A spring adds H_q (v_a - v_b) to a and subtracts it from b.
  const int m = topology_.springs();
  const int n = topology_.vertices;
  const int* a = topology_.a.data();
  const int* b = topology_.b.data();
  tbb::parallel_for(tbb::blocked_range<int>(0, m, kGrain), [&](const tbb::blocked_range<int>& range) {
    for (int q = range.begin(); q != range.end(); ++q) {
      const double* h = &spring_hessian_[6 * static_cast<size_t>(q)];
      const double d0 = v[3 * a[q]] - v[3 * b[q]];
      const double d1 = v[3 * a[q] + 1] - v[3 * b[q] + 1];
      const double d2 = v[3 * a[q] + 2] - v[3 * b[q] + 2];
      double* out = &spring_product_[3 * static_cast<size_t>(q)];
      out[0] = h[0] * d0 + h[1] * d1 + h[2] * d2;
      out[1] = h[1] * d0 + h[3] * d1 + h[4] * d2;
      out[2] = h[2] * d0 + h[4] * d1 + h[5] * d2;
    }
  });
  const int* offsets = topology_.vertex_spring_offsets.data();
  const int* incident = topology_.vertex_springs.data();
  tbb::parallel_for(tbb::blocked_range<int>(0, n, kGrain), [&](const tbb::blocked_range<int>& range) {
    for (int vtx = range.begin(); vtx != range.end(); ++vtx) {
      double sum[3] = {0.0, 0.0, 0.0};
      for (int e = offsets[vtx]; e < offsets[vtx + 1]; ++e) {
        const int q = incident[e];
        const double sign = a[q] == vtx ? 1.0 : -1.0;
        const double* t = &spring_product_[3 * static_cast<size_t>(q)];
        for (int c = 0; c < 3; ++c) sum[c] += sign * t[c];
      }
      for (int c = 0; c < 3; ++c) {
        const int d = 3 * vtx + c;
        (*product)[d] = held[d] ? 0.0 : sum[c] + shift * v[d];
      }
    }
  });
}

void SpringSystem::HessianProducts(const Columns& v, const std::vector<char>& held, double shift,
                                   Columns* product) const {
  // Per vertex: sum over its springs q of H_q (v_vertex - v_other).
  const int n = topology_.vertices;
  const Eigen::Index k = v.cols();
  product->resize(v.rows(), k);
  const int* a = topology_.a.data();
  const int* b = topology_.b.data();
  const int* offsets = topology_.vertex_spring_offsets.data();
  const int* incident = topology_.vertex_springs.data();
  const double* in = v.data();
  double* out = product->data();
  tbb::parallel_for(tbb::blocked_range<int>(0, n, kGrain / 8), [&](const tbb::blocked_range<int>& range) {
    std::vector<double> sum(3 * static_cast<size_t>(k));
    for (int vtx = range.begin(); vtx != range.end(); ++vtx) {
      std::fill(sum.begin(), sum.end(), 0.0);
      const double* here = in + 3 * static_cast<Eigen::Index>(vtx) * k;
      for (int e = offsets[vtx]; e < offsets[vtx + 1]; ++e) {
        const int q = incident[e];
        const int other = a[q] == vtx ? b[q] : a[q];
        const double* h = &spring_hessian_[6 * static_cast<size_t>(q)];
        const double* there = in + 3 * static_cast<Eigen::Index>(other) * k;
        double* s0 = sum.data();
        double* s1 = s0 + k;
        double* s2 = s1 + k;
        for (Eigen::Index j = 0; j < k; ++j) {
          const double d0 = here[j] - there[j];
          const double d1 = here[k + j] - there[k + j];
          const double d2 = here[2 * k + j] - there[2 * k + j];
          s0[j] += h[0] * d0 + h[1] * d1 + h[2] * d2;
          s1[j] += h[1] * d0 + h[3] * d1 + h[4] * d2;
          s2[j] += h[2] * d0 + h[4] * d1 + h[5] * d2;
        }
      }
      for (int c = 0; c < 3; ++c) {
        const Eigen::Index row = 3 * static_cast<Eigen::Index>(vtx) + c;
        double* o = out + row * k;
        const double* x = in + row * k;
        for (Eigen::Index j = 0; j < k; ++j) o[j] = held[row] ? 0.0 : sum[c * k + j] + shift * x[j];
      }
    }
  });
}

}  // namespace springblend::internal
