// The adaptive noise of one filter (server/estimation/adaptive.py's NoiseAdapter, which the tests
// hold this to): R from the fourth differences of the innovations, Q's diagonal by Sage-Husa with
// fading memory, lambda and mu (the factors on Q, and on Q over a gap) from the NIS, and the NIS
// window that asks for an absorption. One per filter, one thread at a time.
#ifndef JITDYN_SERVER_ESTIMATION_NATIVE_ADAPTIVE_H_
#define JITDYN_SERVER_ESTIMATION_NATIVE_ADAPTIVE_H_

#include <Eigen/Dense>

#include <deque>
#include <vector>

namespace jitdyn {

using AdapterMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// adaptive.py's AdaptationBounds.
struct AdapterBounds {
  double r_min, r_max, q_scale_min, q_scale_max, forgetting;
  int window;
  double report_change;
  int window_r, min_differences;
  double inflation_min, inflation_max, inflation_gain, inflation_leak, inflation_step;
  double gap_gain, gap_step, absorb_factor;
};

// Everything an Adapter learns: what a snapshot holds.
struct AdapterState {
  Eigen::VectorXd r, q_est;
  long count = 0;
  Eigen::VectorXd nis;
  long nis_count = 0;
  std::deque<Eigen::VectorXd> recent;
  AdapterMatrix d4;
  long d4_count = 0;
  Eigen::VectorXd reported_r, reported_s;
  double log_inflation = 0.0, log_gap_inflation = 0.0, reported_inflation = 1.0;
};

class Adapter {
 public:
  // r0 (m,) > 0; q0 (n, n); adapt_q (n,); nis_limit: the NIS window's mean past which it absorbs.
  Adapter(const Eigen::VectorXd& r0, const AdapterMatrix& q0, const std::vector<bool>& adapt_q, bool inflate,
          const AdapterBounds& bounds, double nis_limit);

  void Reset();
  // One update: innovation y (m,), gain K (n, m), nis (NaN: none). Returns {adapted, absorb}.
  std::pair<bool, bool> Observe(const Eigen::VectorXd& innovation, bool consecutive, const AdapterMatrix& gain,
                                double nis, double noise_share);
  void ObserveGap(double nis, int m);
  void Absorbed();

  bool window_full() const { return state_.nis_count >= bounds_.window; }
  const Eigen::VectorXd& r() const { return state_.r; }
  Eigen::VectorXd Scale() const;
  double Inflation() const;
  double GapInflation() const;
  // lambda S^1/2 q0 S^1/2 for this or another horizon's configured q0.
  AdapterMatrix QFor(const AdapterMatrix& q0) const;
  const AdapterMatrix& q0() const { return q0_; }

  const AdapterState& state() const { return state_; }
  void Restore(const AdapterState& state) { state_ = state; }

 private:
  void LearnR(const Eigen::VectorXd& y, bool consecutive);
  bool LearnNis(double nis, int m, double noise_share);
  bool Moved();

  AdapterBounds bounds_;
  bool inflate_;
  Eigen::VectorXd r0_;
  AdapterMatrix q0_;
  Eigen::VectorXd q0_diag_;
  std::vector<bool> q_free_;
  double nis_limit_;
  AdapterState state_;
};

}  // namespace jitdyn

#endif  // JITDYN_SERVER_ESTIMATION_NATIVE_ADAPTIVE_H_
