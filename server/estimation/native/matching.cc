// See matching.h. Mirrors server/estimation/matching.py step for step.
#include "matching.h"

#include "extrapolators.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace jitdyn {
namespace {

constexpr double kWindow = 20.0;
constexpr double kCandidateEvery = 0.01;
constexpr double kLag = 0.15;
constexpr double kFade = 0.1;
constexpr double kRewindMargin = 2.0;
constexpr double kSpreadRate = kCandidateEvery / kWindow;
constexpr int kLags = 4;

// Python's round() of a float: halves to even (the default rounding mode).
int Round(double x) { return static_cast<int>(std::nearbyint(x)); }

}  // namespace

MotionMatcher::MotionMatcher(int nv, double dt, int horizon) : nv_(nv), horizon_(horizon), dt_(dt) {
  if (nv < 1 || !(dt > 0.0) || horizon < 1) {
    throw std::invalid_argument("nv, dt and horizon must be positive, got " + std::to_string(nv) + ", " +
                                std::to_string(dt) + ", " + std::to_string(horizon));
  }
  window_ = std::max(2 * horizon, Round(kWindow / dt));
  capacity_ = window_ + horizon + Round(kRewindMargin / dt) + 1;
  every_ = std::max(1, Round(kCandidateEvery / dt));
  const int lag = std::max(kLags - 1, Round(kLag / dt));
  for (int i = 0; i < kLags; ++i) lags_[i] = Round(static_cast<double>(i * lag) / (kLags - 1));
  slots_ = (capacity_ + every_ - 1) / every_;
  width_ = (kLags + 1) * nv_;
  stamp_.assign(capacity_, -1);
  cstamp_.assign(slots_, -1);
  q_ = Matrix::Zero(capacity_, nv_);
  v_ = Matrix::Zero(capacity_, nv_);
  a_ = Matrix::Zero(capacity_, nv_);
  features_ = Matrix::Zero(slots_, width_);
  moments_ = Vector::Zero(2 * width_);
  query_ = Vector::Zero(width_);
  inverse_ = Vector::Zero(width_);
  distance_ = Vector::Zero(slots_);
  order_.resize(slots_);
}

std::int64_t MotionMatcher::Row(std::int64_t tick) const {
  const std::int64_t r = tick % capacity_;
  return r < 0 ? r + capacity_ : r;
}

void MotionMatcher::Restore(const Vector& state) {
  if (state.size() != moments_.size()) {
    throw std::invalid_argument("state must have " + std::to_string(moments_.size()) + " entries, got " +
                                std::to_string(state.size()));
  }
  moments_ = state;
}

void MotionMatcher::Record(std::int64_t tick, const double* qpos, const double* qvel) {
  const std::int64_t row = Row(tick), previous = Row(tick - 1);
  stamp_[row] = tick;
  for (int j = 0; j < nv_; ++j) {
    q_(row, j) = qpos[j];
    v_(row, j) = qvel[j];
  }
  // qdd by the backward difference of qd (0 after a hole).
  const bool follows = stamp_[previous] == tick - 1;
  for (int j = 0; j < nv_; ++j) a_(row, j) = follows ? (qvel[j] - v_(previous, j)) / dt_ : 0.0;
  if (tick % every_ != 0) return;
  const std::int64_t slot = (tick / every_) % slots_;
  const bool found = Feature(tick, query_.data());
  cstamp_[slot] = found ? tick : -1;
  if (!found) return;
  features_.row(slot) = query_.transpose();
  for (int j = 0; j < width_; ++j) {
    double& mean = moments_[j];
    double& variance = moments_[width_ + j];
    mean += kSpreadRate * (query_[j] - mean);
    const double d = query_[j] - mean;
    variance += kSpreadRate * (d * d - variance);
  }
}

bool MotionMatcher::Feature(std::int64_t tick, double* out) const {
  std::array<std::int64_t, kLags> rows;
  for (int i = 0; i < kLags; ++i) {
    rows[i] = Row(tick - lags_[i]);
    if (stamp_[rows[i]] != tick - lags_[i]) return false;
  }
  for (int i = 0; i < kLags; ++i) {
    for (int j = 0; j < nv_; ++j) out[i * nv_ + j] = q_(rows[i], j);
  }
  for (int j = 0; j < nv_; ++j) out[kLags * nv_ + j] = v_(rows[0], j);
  return true;
}

bool MotionMatcher::Match(std::int64_t tick, double* ticks, double* weights) {
  if (!Feature(tick, query_.data())) return false;
  int in = 0;
  for (int s = 0; s < slots_; ++s) {
    const std::int64_t c = cstamp_[s];
    if (!(c <= tick - window_ || c > tick - horizon_)) ++in;
  }
  if (in < kMatchK) return false;
  constexpr double kInf = std::numeric_limits<double>::infinity();
  // Each feature by its spread.
  for (int j = 0; j < width_; ++j) inverse_[j] = 1.0 / std::max(moments_[width_ + j], 1e-18);
  for (int s = 0; s < slots_; ++s) {
    const std::int64_t c = cstamp_[s];
    if (c <= tick - window_ || c > tick - horizon_) {
      distance_[s] = kInf;
      continue;
    }
    double sum = 0.0;
    for (int j = 0; j < width_; ++j) {
      const double d = features_(s, j) - query_[j];
      sum += d * d * inverse_[j];
    }
    distance_[s] = sum;
  }
  for (int s = 0; s < slots_; ++s) order_[s] = s;
  std::nth_element(order_.begin(), order_.begin() + (kMatchK - 1), order_.end(),
                   [&](int a, int b) { return distance_[a] < distance_[b]; });
  double least = kInf;
  for (int k = 0; k < kMatchK; ++k) least = std::min(least, distance_[order_[k]]);
  double total = 0.0;
  for (int k = 0; k < kMatchK; ++k) {
    weights[k] = 1.0 / (distance_[order_[k]] + 1e-3 * least + 1e-12);
    total += weights[k];
  }
  for (int k = 0; k < kMatchK; ++k) {
    weights[k] /= total;
    ticks[k] = static_cast<double>(cstamp_[order_[k]]);
  }
  return true;
}

void MotionMatcher::Follow(const double* ticks, const double* weights, std::int64_t age, const double* q0,
                           const double* v0, double* q, double* v, double* a) const {
  const double t = static_cast<double>(age) * dt_;
  if (std::isnan(ticks[0])) {  // no match: CONSTANT_VELOCITY
    for (int j = 0; j < nv_; ++j) Extrapolate(Extrapolator::kConstantVelocity, q0[j], v0[j], 0.0, t, &q[j], &v[j], &a[j]);
    return;
  }
  std::array<std::int64_t, kMatchK> r0, r1;
  std::array<double, kMatchK> w;
  double total = 0.0;
  for (int k = 0; k < kMatchK; ++k) {
    const std::int64_t start = static_cast<std::int64_t>(ticks[k]), later = start + age;
    r0[k] = Row(start);
    r1[k] = Row(later);
    w[k] = stamp_[r1[k]] == later ? weights[k] : 0.0;
    total += w[k];
  }
  if (total == 0.0) {
    for (int j = 0; j < nv_; ++j) {
      q[j] = q0[j] + v0[j] * t;
      v[j] = v0[j];
      a[j] = 0.0;
    }
    return;
  }
  for (int k = 0; k < kMatchK; ++k) w[k] /= total;
  const double fade = std::exp(-t / kFade);
  for (int j = 0; j < nv_; ++j) {
    double start_v = 0.0, dq = 0.0, dv = 0.0, acc = 0.0;
    for (int k = 0; k < kMatchK; ++k) {
      start_v += weights[k] * v_(r0[k], j);
      dq += w[k] * (q_(r1[k], j) - q_(r0[k], j));
      dv += w[k] * (v_(r1[k], j) - v_(r0[k], j));
      acc += w[k] * a_(r1[k], j);
    }
    const double dv0 = v0[j] - start_v;
    q[j] = q0[j] + dq + dv0 * (kFade * (1.0 - fade));
    v[j] = v0[j] + dv - dv0 * (1.0 - fade);
    a[j] = acc - dv0 * (fade / kFade);
  }
}

}  // namespace jitdyn
