// See adaptive.h; each step follows server/estimation/adaptive.py's of the same name.
#include "adaptive.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace jitdyn {
namespace {

constexpr double kMadToSigma = 1.4826;  // median |N(0, 1)| = 0.6745 = 1 / 1.4826
constexpr double kD4Variance = 70.0;    // var of the fourth difference of unit white noise

double Clip(double value, double low, double high) { return std::min(std::max(value, low), high); }

// np.median(a, axis=0): the middle value, or the mean of the two middle ones.
Eigen::VectorXd ColumnMedians(const AdapterMatrix& a) {
  const Eigen::Index k = a.rows();
  Eigen::VectorXd out(a.cols());
  std::vector<double> column(k);
  for (Eigen::Index j = 0; j < a.cols(); ++j) {
    for (Eigen::Index i = 0; i < k; ++i) column[i] = a(i, j);
    const Eigen::Index half = k / 2;
    std::nth_element(column.begin(), column.begin() + half, column.end());
    const double upper = column[half];
    if (k % 2) {
      out[j] = upper;
    } else {
      const double lower = *std::max_element(column.begin(), column.begin() + half);
      out[j] = (lower + upper) / 2.0;
    }
  }
  return out;
}

}  // namespace

Adapter::Adapter(const Eigen::VectorXd& r0, const AdapterMatrix& q0, const std::vector<bool>& adapt_q,
                 bool inflate, const AdapterBounds& bounds, double nis_limit)
    : bounds_(bounds), inflate_(inflate), q0_(q0), nis_limit_(nis_limit) {
  if (r0.size() == 0 || (r0.array() <= 0.0).any()) throw std::invalid_argument("r0 must be positive variances");
  if (q0.rows() != q0.cols()) throw std::invalid_argument("q0 must be square");
  if (static_cast<Eigen::Index>(adapt_q.size()) != q0.rows()) throw std::invalid_argument("adapt_q must be (n,)");
  r0_ = r0.cwiseMax(bounds.r_min).cwiseMin(bounds.r_max);
  const Eigen::VectorXd diag = q0.diagonal();
  q0_diag_ = diag;
  q_free_.resize(diag.size());
  for (Eigen::Index i = 0; i < diag.size(); ++i) {
    // A component with no configured noise gets none: there is no scale to adapt.
    if (!(diag[i] > 0.0)) q0_diag_[i] = 1.0;
    q_free_[i] = diag[i] > 0.0 && adapt_q[i];
  }
  Reset();
}

void Adapter::Reset() {
  AdapterState s;
  s.r = r0_;
  s.q_est = q0_.diagonal();
  s.nis = Eigen::VectorXd::Zero(bounds_.window);
  s.d4 = AdapterMatrix::Zero(bounds_.window_r, r0_.size());
  s.reported_r = s.r;
  s.reported_s = Eigen::VectorXd::Ones(s.q_est.size());
  state_ = std::move(s);
}

Eigen::VectorXd Adapter::Scale() const {
  Eigen::VectorXd s(state_.q_est.size());
  for (Eigen::Index i = 0; i < s.size(); ++i) {
    const double value = q_free_[i] ? state_.q_est[i] / q0_diag_[i] : 1.0;
    s[i] = Clip(value, bounds_.q_scale_min, bounds_.q_scale_max);
  }
  return s;
}

double Adapter::Inflation() const { return std::exp(state_.log_inflation); }
double Adapter::GapInflation() const { return std::exp(state_.log_gap_inflation); }

AdapterMatrix Adapter::QFor(const AdapterMatrix& q0) const {
  if (q0.rows() != q0_.rows() || q0.cols() != q0_.cols()) throw std::invalid_argument("q0 must be (n, n)");
  const Eigen::VectorXd root = (Scale() * Inflation()).array().sqrt();
  AdapterMatrix out(q0.rows(), q0.cols());
  for (Eigen::Index i = 0; i < q0.rows(); ++i) {
    for (Eigen::Index j = 0; j < q0.cols(); ++j) out(i, j) = root[i] * q0(i, j) * root[j];
  }
  return out;
}

std::pair<bool, bool> Adapter::Observe(const Eigen::VectorXd& innovation, bool consecutive,
                                       const AdapterMatrix& gain, double nis, double noise_share) {
  if (!innovation.allFinite()) return {false, false};
  if (gain.rows() != state_.q_est.size() || gain.cols() != innovation.size()) {
    throw std::invalid_argument("gain must be (n, m)");
  }
  AdapterState& s = state_;
  const double f = bounds_.forgetting;
  const double d = (1.0 - f) / (1.0 - std::pow(f, static_cast<double>(s.count + 1)));
  s.count += 1;
  LearnR(innovation, consecutive);
  const Eigen::VectorXd correction = gain * innovation;
  const Eigen::VectorXd q_next = (1.0 - d) * s.q_est.array() + d * correction.array().square();
  if (q_next.allFinite()) s.q_est = q_next;
  bool absorb = false;
  if (std::isfinite(nis)) absorb = LearnNis(nis, static_cast<int>(innovation.size()), noise_share);
  return {Moved(), absorb};
}

void Adapter::LearnR(const Eigen::VectorXd& y, bool consecutive) {
  AdapterState& s = state_;
  if (!consecutive) s.recent.clear();
  s.recent.push_back(y);
  if (s.recent.size() > 5) s.recent.pop_front();
  if (s.recent.size() == 5 && y.size() == s.r.size()) {
    const auto& r = s.recent;
    s.d4.row(s.d4_count % bounds_.window_r) =
        (r[4].array() - 4.0 * r[3].array() + 6.0 * r[2].array() - 4.0 * r[1].array() + r[0].array()).matrix().transpose();
    s.d4_count += 1;
    if (s.d4_count >= bounds_.min_differences) {
      const long rows = std::min<long>(s.d4_count, bounds_.window_r);
      const Eigen::VectorXd scale = kMadToSigma * ColumnMedians(s.d4.topRows(rows).cwiseAbs()).array();
      s.r = (scale.array().square() / kD4Variance).cwiseMax(bounds_.r_min).cwiseMin(bounds_.r_max);
    }
  }
}

bool Adapter::LearnNis(double nis, int m, double noise_share) {
  AdapterState& s = state_;
  const AdapterBounds& b = bounds_;
  if (nis >= 0.0 && inflate_) {
    const double share = std::min(std::max(1.0 - noise_share, 0.0), 1.0);
    double step = b.inflation_gain * share * (nis / m - 1.0);
    step = std::min(std::max(step, -b.inflation_step), b.inflation_step);
    const double low = std::log(b.inflation_min), high = std::log(b.inflation_max);
    const double leaked = (1.0 - b.inflation_leak) * s.log_inflation;
    s.log_inflation = std::min(std::max(leaked + step, low), high);
  }
  s.nis[s.nis_count % b.window] = nis;
  s.nis_count += 1;
  if (s.nis_count < b.window) return false;
  return s.nis.mean() > nis_limit_;
}

bool Adapter::Moved() {
  AdapterState& s = state_;
  const double change = bounds_.report_change;
  const Eigen::VectorXd scale = Scale();
  const double inflation = Inflation();
  const bool moved = ((s.r - s.reported_r).cwiseAbs().array() > change * s.reported_r.array()).any() ||
                     ((scale - s.reported_s).cwiseAbs().array() > change * s.reported_s.array()).any() ||
                     std::abs(inflation - s.reported_inflation) > change * s.reported_inflation;
  if (moved) {
    s.reported_r = s.r;
    s.reported_s = scale;
    s.reported_inflation = inflation;
  }
  return moved;
}

void Adapter::ObserveGap(double nis, int m) {
  const AdapterBounds& b = bounds_;
  if (!(inflate_ && std::isfinite(nis) && nis >= 0.0)) return;
  const double step = std::min(std::max(b.gap_gain * (nis / m - 1.0), -b.gap_step), b.gap_step);
  const double low = std::log(b.inflation_min), high = std::log(b.inflation_max);
  state_.log_gap_inflation = std::min(std::max(state_.log_gap_inflation + step, low), high);
}

void Adapter::Absorbed() {
  AdapterState& s = state_;
  s.q_est = (s.q_est * bounds_.absorb_factor).cwiseMin(q0_diag_ * bounds_.q_scale_max);
  s.nis.setZero();
  s.nis_count = 0;
}

}  // namespace jitdyn
