// The forecast combination of a DRIVEN session with the default predictors, as
// server/estimation/forecast.py's ForecastCombiner computes it (tests/server/test_native_forecast.py
// holds the two to 1e-9): MODEL (the posterior rolled out by mj_step on the process model, its force
// held or ramped with its rate), IEEE 1278's STATIC, CONSTANT_VELOCITY and CONSTANT_ACCELERATION,
// LEARNED (motion matching, matching.h) and, for a model whose joints have leg roles, PRIOR (the prior
// of human motion, prior.h); probes scored against each frame into fading pooled
// covariances; the minimum-variance weights over every subset; the novelty guard; the answer's
// variances net of the frames' noise. One instance per session, one thread at a time.
#ifndef JITDYN_SERVER_ESTIMATION_NATIVE_FORECAST_H_
#define JITDYN_SERVER_ESTIMATION_NATIVE_FORECAST_H_

#include <Eigen/Dense>
#include <mujoco/mujoco.h>

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <vector>

#include "matching.h"
#include "prior.h"
#include "ukf.h"

namespace jitdyn {

// The predictors, in the weights' order (forecast.py's PREDICTORS, then LEARNED, then PRIOR when the
// combiner has the prior): at most kPredictors, the matrices sized for them.
constexpr int kPredictors = 6;
using PMatrix = Eigen::Matrix<double, kPredictors, kPredictors, Eigen::RowMajor>;
using PVector = Eigen::Matrix<double, kPredictors, 1>;

// The combination's answer (forecast.py's CombinedForecast).
struct CombinedForecast {
  PVector weights;
  Vector qpos, qvel, qacc, var_q, var_qd;
};

// A Combiner's whole state (forecast.py's CombinerSnapshot, its scorings already reckoned): opaque
// and immutable from Python.
struct CombinerState {
  std::int64_t tick = 0;
  Matrix table;                                   // (n, width) the live probes
  std::vector<std::array<std::int64_t, 5>> marks;  // (n,) origin, age, keep, ramp, matched
  std::vector<PMatrix> cov, cov_v;
  std::vector<double> count, learned_count;
  bool has_anchor = false;
  Vector anchor_q, anchor_v;
  std::int64_t anchor_tick = -1;
  Vector learner;  // the matcher's moments
  PriorRing prior;  // the prior's ring of frames (empty without the prior)
  std::size_t Bytes() const;
};

class Combiner {
 public:
  // prior: the prior of human motion's matcher and its scores over STATIC, the other extrapolators
  // and PRIOR at every horizon 0..horizon ((horizon + 1) 4 x 4 each; empty: none), or nothing.
  Combiner(const mjModel* model, double dt, int steps_per_tick, int horizon,
           std::unique_ptr<PriorMatcher> prior = nullptr, std::vector<Eigen::Matrix4d> prior_cov = {},
           std::vector<Eigen::Matrix4d> prior_cov_v = {});
  ~Combiner();
  Combiner(const Combiner&) = delete;
  Combiner& operator=(const Combiner&) = delete;

  void Reset();
  // One tick passes: every probe carried one tick forward.
  void Advance();
  // A frame (qpos, qvel) at this tick and the filter's posterior after it (rate empty: held force).
  void Observe(const Vector& qpos, const Vector& qvel, const Vector& mean_qpos, const Vector& mean_qvel,
               const Vector& act, const Vector& force, const std::optional<Vector>& rate);
  // The answer now, or nothing (the filter answers); noise empty: nothing taken out.
  std::optional<CombinedForecast> Forecast(const std::optional<Vector>& noise_q,
                                           const std::optional<Vector>& noise_qd, bool ended);
  // Ticks pass with the matcher's window of frames recorded (rows of q and qd); the tick reached.
  std::int64_t FillWindow(const Matrix& q, const Matrix& v);

  CombinerState Snapshot() const;
  void Restore(const CombinerState& state);

  int horizon() const { return horizon_; }
  int nv() const { return nv_; }
  int na() const { return na_; }
  int window() const { return matcher_.window(); }
  int predictors() const { return p_; }
  std::int64_t tick() const { return tick_; }

 private:
  struct Columns {
    int qpos, qvel, qacc, act, force, rate, q0, v0, a0, match_ticks, match_weights, prior_rows, prior_weights,
        width;
  };
  // Every predictor's qpos, qvel, qacc (P, nv) for probe row i at its age.
  void Predict(int i);
  void Score(int i, const Vector& qpos, const Vector& qvel);
  void Step(int i);
  void MatchProbe(int i);
  void Grow(int capacity);
  void SetPriorScores(const std::vector<Eigen::Matrix4d>& cov, const std::vector<Eigen::Matrix4d>& cov_v);
  bool Surprised(std::int64_t h, const PMatrix& c) const;
  PVector SolveWeights(std::int64_t h, const PVector* scale, bool matched = true) const;
  // The covariances of q and qd errors the weights of horizon h come from (forecast.py's _weighing).
  std::array<PMatrix, 2> Weighing(std::int64_t h) const;

  const mjModel* m_;
  mjData* d_;
  std::vector<mjtNum> template_;  // a fresh mjData's FULLPHYSICS state
  int qpos_at_, qvel_at_, act_at_;
  double dt_, h_;
  int nstep_, horizon_, stride_, nq_, nv_, na_;
  Columns c_;
  MotionMatcher matcher_;
  std::unique_ptr<PriorMatcher> prior_;
  std::vector<PMatrix> prior_cov_, prior_cov_v_;  // the prior's scores, empty without them
  int p_;                                          // the predictors: 5, 6 with the prior

  std::int64_t tick_ = 0;
  int n_ = 0;
  Matrix table_;
  std::vector<std::array<std::int64_t, 5>> marks_;
  std::vector<PMatrix> cov_, cov_v_;
  std::vector<double> count_, learned_count_;
  // The weights and scored variances of each horizon, while its covariances have not changed.
  std::vector<bool> cached_, var_cached_;
  std::vector<PVector> weights_;
  std::vector<std::array<double, 2>> variances_;
  bool has_anchor_ = false;
  Vector anchor_q_, anchor_v_;
  std::int64_t anchor_tick_ = -1;
  // Scratch, sized once: the predictors' answers of one probe and their errors; LEARNED's; a0; the
  // novelty guard's reference position.
  Matrix pq_, pv_, pa_, errors_, verrors_;
  Vector lq_, lv_, la_, a0_, at_;
};

}  // namespace jitdyn

#endif  // JITDYN_SERVER_ESTIMATION_NATIVE_FORECAST_H_
