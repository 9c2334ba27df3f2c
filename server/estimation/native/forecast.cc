// See forecast.h. Mirrors server/estimation/forecast.py's ForecastCombiner; a
// frame's scoring is reckoned when it comes (forecast.py's PENDING batching gives the same numbers,
// and is only there to spare Python calls).
#include "forecast.h"

#include <Eigen/LU>

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "extrapolators.h"

namespace jitdyn {
namespace {

// forecast.py's MIN_SAMPLES, LEARNED_SAMPLES, FORGETTING, PROBES, MAX_NOISE_SHARE, VARIANCE_FLOOR,
// NOVELTY, MAX_NOVELTY, SURPRISE, SETTLED.
constexpr double kMinSamples = 3.0;
constexpr double kLearnedSamples = 5.0;
constexpr double kForgetting = 0.8;
constexpr int kProbes = 16;
constexpr double kMaxNoiseShare = 0.9;
constexpr double kVarianceFloor = 1e-12;
constexpr double kNovelty = 2.0;
constexpr double kMaxNovelty = 1e3;
constexpr double kSurprise = 2.0;
constexpr double kSettled = 12.0;
// The predictors' rows: MODEL, the extrapolators (STATIC first), LEARNED, PRIOR; which vote on a
// regime change (the first kFixed); the prior's scores' block (PriorScores' order).
constexpr int kModel = 0, kStatic = 1, kAcceleration = 3, kLearned = 4, kPrior = 5, kFixed = 4;
constexpr std::array<int, 4> kPriorBlock = {1, 2, 3, kPrior};
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
// The probes' integer marks.
constexpr int kOrigin = 0, kAge = 1, kKeep = 2, kRamp = 3, kMatched = 4;

// forecast.py's _FADING: Sage and Husa's fading weight after `count` samples, by C's pow as
// Python's scalar power, until it no longer changes.
const std::vector<double>& Fading() {
  static const std::vector<double> table = [] {
    std::vector<double> out;
    for (double count = 0.0;; count += 1.0) {
      const double d = (1.0 - kForgetting) / (1.0 - std::pow(kForgetting, count + 1.0));
      if (d == 1.0 - kForgetting) break;
      out.push_back(d);
    }
    out.push_back(1.0 - kForgetting);
    return out;
  }();
  return table;
}

// forecast.py's _confirmed: how far the last two frames' velocities agree, in [0, 1]: v0 and the
// velocity one tick before it, v0 - a0 dt, their product over the larger square; 0 for a still
// frame. Expressions, no allocation.
template <typename V, typename A>
double Confirmed(const Eigen::MatrixBase<V>& v0, const Eigen::MatrixBase<A>& a0, double dt) {
  const double larger = std::max(v0.dot(v0), (v0 - a0 * dt).squaredNorm());
  if (!(larger > 0.0)) return 0.0;
  return std::min(std::max(v0.dot(v0 - a0 * dt) / larger, 0.0), 1.0);
}

// Every subset of range(p), by size, each size in itertools.combinations' order.
std::vector<std::vector<int>> Subsets(int p) {
  std::vector<std::vector<int>> out;
  for (int size = 1; size <= p; ++size) {
    std::vector<int> pick(size);
    for (int i = 0; i < size; ++i) pick[i] = i;
    while (true) {
      out.push_back(pick);
      int i = size - 1;
      while (i >= 0 && pick[i] == p - size + i) --i;
      if (i < 0) break;
      ++pick[i];
      for (int j = i + 1; j < size; ++j) pick[j] = pick[j - 1] + 1;
    }
  }
  return out;
}

// A subset's system, on the stack (at most P x P).
using SmallMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::ColMajor, kPredictors, kPredictors>;
using SmallVector = Eigen::Matrix<double, Eigen::Dynamic, 1, Eigen::ColMajor, kPredictors, 1>;

// forecast.py's _min_variance_weights: argmin w' C w over w >= 0, sum w = 1, for the leading p
// predictors of C (the rest weigh 0).
PVector MinVarianceWeights(const PMatrix& full, int p) {
  static const std::array<std::vector<std::vector<int>>, kPredictors + 1> subsets = [] {
    std::array<std::vector<std::vector<int>>, kPredictors + 1> out;
    for (int k = 1; k <= kPredictors; ++k) out[k] = Subsets(k);
    return out;
  }();
  PVector best = PVector::Zero();
  const double scale = full.topLeftCorner(p, p).trace() / p;
  if (!std::isfinite(scale) || scale <= 0.0) {
    best[0] = 1.0;
    return best;
  }
  // A little ridge keeps near-collinear predictors (CV and CA over one tick) from extreme weights.
  PMatrix C = full;
  for (int i = 0; i < p; ++i) C(i, i) += 1e-9 * scale;
  double best_v = std::numeric_limits<double>::infinity();
  bool found = false;
  for (const std::vector<int>& subset : subsets[p]) {
    const int k = static_cast<int>(subset.size());
    SmallMatrix A(k, k);
    for (int i = 0; i < k; ++i) {
      for (int j = 0; j < k; ++j) A(i, j) = C(subset[i], subset[j]);
    }
    // LAPACK's gesv: LU with partial pivoting; an exact zero pivot is a singular system.
    Eigen::PartialPivLU<SmallMatrix> lu(A);
    bool singular = false;
    for (int i = 0; i < k; ++i) singular = singular || lu.matrixLU()(i, i) == 0.0;
    if (singular) continue;
    const SmallVector x = lu.solve(SmallVector::Ones(k));
    const double total = x.sum();
    bool nonnegative = true;
    for (int i = 0; i < k; ++i) nonnegative = nonnegative && x[i] >= 0.0;
    if (!(total > 0.0) || !nonnegative) continue;
    PVector w = PVector::Zero();
    for (int i = 0; i < k; ++i) w[subset[i]] = x[i] / total;
    const double v = w.dot(C * w);
    if (v < best_v) {
      best = w;
      best_v = v;
      found = true;
    }
  }
  if (!found) {
    best = PVector::Zero();
    int least = 0;
    for (int i = 1; i < p; ++i) {
      if (C(i, i) < C(least, least)) least = i;
    }
    best[least] = 1.0;
  }
  return best;
}

// MinVarianceWeights over the predictors `allowed` (the first k of it) alone, the others 0.
PVector MinVarianceOver(const PMatrix& C, const std::array<int, kPredictors>& allowed, int k) {
  PMatrix sub = PMatrix::Zero();
  for (int i = 0; i < k; ++i) {
    for (int j = 0; j < k; ++j) sub(i, j) = C(allowed[i], allowed[j]);
  }
  const PVector w = MinVarianceWeights(sub, k);
  PVector out = PVector::Zero();
  for (int i = 0; i < k; ++i) out[allowed[i]] = w[i];
  return out;
}

// forecast.py's _at_scale: the prior's covariance times the session's lowest variance among the
// prior's predictors over the prior's own lowest (as it is where either is nil).
PMatrix AtScale(const PMatrix& prior, const PMatrix& session) {
  double ours = std::numeric_limits<double>::infinity(), theirs = ours;
  for (int p : kPriorBlock) {
    ours = std::min(ours, session(p, p));
    theirs = std::min(theirs, prior(p, p));
  }
  return ours <= 0.0 || theirs <= 0.0 ? prior : PMatrix(prior * (ours / theirs));
}

// forecast.py's _PRIOR_SHARE: FORGETTING^n by C's pow, as Python's scalar power; nil from 200.
double PriorShare(double count) {
  return count >= 200.0 ? 0.0 : std::pow(kForgetting, count);
}

// forecast.py's _agreement: how far the session's own scores at a horizon (`scored`, after `count`
// of them) agree with the prior's: the lowest variance of the prior's predictors over PRIOR's own, at
// most 1 (1 before MIN_SAMPLES scores, or where PRIOR's is nil).
double Agreement(const PMatrix& scored, double count) {
  if (count < kMinSamples) return 1.0;
  double best = std::numeric_limits<double>::infinity();
  for (int p : kPriorBlock) best = std::min(best, scored(p, p));
  const double prior = scored(kPrior, kPrior);
  return !(prior > 0.0) ? 1.0 : std::min(best / prior, 1.0);
}

// forecast.py's _net_of_noise.
Vector NetOfNoise(double scored, const std::optional<Vector>& noise, int nv) {
  if (!noise) return Vector::Constant(nv, std::max(scored, kVarianceFloor));
  Vector out(nv);
  for (int j = 0; j < nv; ++j) {
    out[j] = std::max(std::max(scored - (*noise)[j], (1.0 - kMaxNoiseShare) * scored), kVarianceFloor);
  }
  return out;
}

// Where a component of an mjSTATE_FULLPHYSICS vector starts: components are laid out in bit order.
int StateOffset(const mjModel* m, int component) {
  int offset = 0;
  for (int bit = 0; (1 << bit) < component; ++bit) {
    if ((1 << bit) & mjSTATE_FULLPHYSICS) offset += mj_stateSize(m, 1 << bit);
  }
  return offset;
}

void Require(bool condition, const std::string& message) {
  if (!condition) throw std::invalid_argument(message);
}

void RequireSize(const Vector& v, int size, const char* name) {
  Require(v.size() == size, std::string(name) + " must have " + std::to_string(size) + " entries, got " +
                                std::to_string(v.size()));
}

}  // namespace

std::size_t CombinerState::Bytes() const {
  return sizeof(double) * (table.size() + 5 * marks.size() + 2 * cov.size() * kPredictors * kPredictors +
                           count.size() + learned_count.size() + anchor_q.size() + anchor_v.size() +
                           learner.size() + prior.stamp.size() + prior.q.size() + prior.v.size());
}

Combiner::Combiner(const mjModel* model, double dt, int steps_per_tick, int horizon,
                   std::unique_ptr<PriorMatcher> prior, std::vector<Eigen::Matrix4d> prior_cov,
                   std::vector<Eigen::Matrix4d> prior_cov_v)
    : m_(model),
      d_(nullptr),
      dt_(dt),
      h_(model->opt.timestep),
      nstep_(steps_per_tick),
      horizon_(std::max(1, horizon)),
      stride_(std::max(1, (std::max(1, horizon) + kProbes - 1) / kProbes)),
      nq_(model->nq),
      nv_(model->nv),
      na_(model->na),
      matcher_(model->nv, dt, std::max(1, horizon)),
      prior_(std::move(prior)),
      p_(prior_ ? kPredictors : kPredictors - 1) {
  Require(nq_ == nv_, "the forecast combination needs nq == nv (no ball or free joints)");
  Require(nstep_ >= 1, "steps_per_tick must be >= 1, got " + std::to_string(nstep_));
  d_ = mj_makeData(m_);
  Require(d_ != nullptr, "could not allocate mjData");
  template_.resize(mj_stateSize(m_, mjSTATE_FULLPHYSICS));
  mj_getState(m_, d_, template_.data(), mjSTATE_FULLPHYSICS);
  qpos_at_ = StateOffset(m_, mjSTATE_QPOS);
  qvel_at_ = StateOffset(m_, mjSTATE_QVEL);
  act_at_ = StateOffset(m_, mjSTATE_ACT);
  int at = 0;
  auto next = [&at](int size) {
    const int start = at;
    at += size;
    return start;
  };
  c_.qpos = next(nq_);
  c_.qvel = next(nv_);
  c_.qacc = next(nv_);
  c_.act = next(na_);
  c_.force = next(nv_);
  c_.rate = next(nv_);
  c_.q0 = next(nv_);
  c_.v0 = next(nv_);
  c_.a0 = next(nv_);
  c_.match_ticks = next(kMatchK);
  c_.match_weights = next(kMatchK);
  const int prior_width = prior_ ? prior_->legs() * kPriorK : 0;
  c_.prior_rows = next(prior_width);
  c_.prior_weights = next(prior_width);
  c_.width = at;
  SetPriorScores(prior_cov, prior_cov_v);
  pq_ = Matrix::Zero(p_, nv_);
  pv_ = Matrix::Zero(p_, nv_);
  pa_ = Matrix::Zero(p_, nv_);
  errors_ = verrors_ = Matrix::Zero(p_, nv_);
  lq_ = lv_ = la_ = a0_ = at_ = anchor_q_ = anchor_v_ = Vector::Zero(nv_);
  Grow((horizon_ + stride_ - 1) / stride_ + 3);
  Reset();
}

Combiner::~Combiner() {
  if (d_) mj_deleteData(d_);
}

void Combiner::Grow(int capacity) {
  table_.conservativeResize(capacity, c_.width);
  marks_.resize(capacity);
}

void Combiner::Reset() {
  tick_ = 0;
  n_ = 0;
  cov_.assign(horizon_ + 1, PMatrix::Zero());
  cov_v_.assign(horizon_ + 1, PMatrix::Zero());
  count_.assign(horizon_ + 1, 0.0);
  learned_count_.assign(horizon_ + 1, 0.0);
  cached_.assign(horizon_ + 1, false);
  var_cached_.assign(horizon_ + 1, false);
  weights_.assign(horizon_ + 1, PVector::Zero());
  variances_.assign(horizon_ + 1, {0.0, 0.0});
  has_anchor_ = false;
  anchor_tick_ = -1;
}

void Combiner::Step(int i) {
  double* row = table_.row(i).data();
  std::vector<mjtNum>& state = template_;
  mju_copy(state.data() + qpos_at_, row + c_.qpos, nq_);
  mju_copy(state.data() + qvel_at_, row + c_.qvel, nv_);
  if (na_) mju_copy(state.data() + act_at_, row + c_.act, na_);
  mj_setState(m_, d_, state.data(), mjSTATE_FULLPHYSICS);
  if (m_->nu) mju_zero(d_->ctrl, m_->nu);  // actuation is off in the process model
  double* force = row + c_.force;
  const double* rate = row + c_.rate;
  if (marks_[i][kRamp] == 0) {
    mju_copy(d_->qfrc_applied, force, nv_);
    for (int s = 0; s < nstep_; ++s) mj_step(m_, d_);
  } else {
    for (int s = 0; s < nstep_; ++s) {
      for (int j = 0; j < nv_; ++j) d_->qfrc_applied[j] = force[j] + (s + 0.5) * h_ * rate[j];
      mj_step(m_, d_);
    }
    for (int j = 0; j < nv_; ++j) force[j] = force[j] + nstep_ * h_ * rate[j];
  }
  mju_copy(row + c_.qpos, d_->qpos, nq_);
  mju_copy(row + c_.qvel, d_->qvel, nv_);
  mju_copy(row + c_.qacc, d_->qacc, nv_);
  if (na_) mju_copy(row + c_.act, d_->act, na_);
}

void Combiner::Advance() {
  ++tick_;
  for (int i = 0; i < n_; ++i) {
    if (marks_[i][kKeep] == 0 || marks_[i][kAge] < horizon_) {
      Step(i);
      ++marks_[i][kAge];
    }
  }
}

void Combiner::MatchProbe(int i) {
  marks_[i][kMatched] = 1;
  double* ticks = table_.row(i).data() + c_.match_ticks;
  double* weights = table_.row(i).data() + c_.match_weights;
  if (prior_) {
    double* row = table_.row(i).data();
    prior_->Match(marks_[i][kOrigin], row + c_.prior_rows, row + c_.prior_weights);
  }
  if (!matcher_.Match(marks_[i][kOrigin], ticks, weights)) {
    for (int k = 0; k < kMatchK; ++k) {
      ticks[k] = kNaN;
      weights[k] = 0.0;
    }
  }
}

void Combiner::Predict(int i) {
  const double* row = table_.row(i).data();
  const std::int64_t age = marks_[i][kAge];
  const double t = static_cast<double>(age) * dt_;
  for (int j = 0; j < nv_; ++j) {
    pq_(kModel, j) = row[c_.qpos + j];
    pv_(kModel, j) = row[c_.qvel + j];
    pa_(kModel, j) = row[c_.qacc + j];
    for (int e = 0; e < 3; ++e) {
      Extrapolate(static_cast<Extrapolator>(e), row[c_.q0 + j], row[c_.v0 + j], row[c_.a0 + j], t,
                  &pq_(kStatic + e, j), &pv_(kStatic + e, j), &pa_(kStatic + e, j));
    }
  }
  matcher_.Follow(row + c_.match_ticks, row + c_.match_weights, age, row + c_.q0, row + c_.v0, lq_.data(),
                  lv_.data(), la_.data());
  pq_.row(kLearned) = lq_.transpose();
  pv_.row(kLearned) = lv_.transpose();
  pa_.row(kLearned) = la_.transpose();
  if (prior_) {  // the dofs of no leg: LEARNED's
    prior_->Follow(row + c_.prior_rows, row + c_.prior_weights, age, row + c_.q0, row + c_.v0, row + c_.a0,
                   lq_.data(), lv_.data(), la_.data());
    pq_.row(kPrior) = lq_.transpose();
    pv_.row(kPrior) = lv_.transpose();
    pa_.row(kPrior) = la_.transpose();
  }
}

bool Combiner::Surprised(std::int64_t h, const PMatrix& c) const {
  if (!(count_[h] >= kMinSamples)) return false;
  for (int p = 0; p < kFixed; ++p) {
    if (!(c(p, p) > kSurprise * kSurprise * cov_[h](p, p))) return false;
  }
  return true;
}

void Combiner::Score(int i, const Vector& qpos, const Vector& qvel) {
  Predict(i);
  const std::int64_t h = marks_[i][kAge];
  if (!std::isnan(table_(i, c_.match_ticks))) learned_count_[h] += 1.0;
  errors_ = pq_.rowwise() - qpos.transpose();
  verrors_ = pv_.rowwise() - qvel.transpose();
  if (!errors_.allFinite() || !verrors_.allFinite()) return;
  // A probe that diverged without going non-finite squares past the largest float: left out.
  PMatrix c = PMatrix::Zero(), cv = PMatrix::Zero();
  c.topLeftCorner(p_, p_).noalias() = errors_ * errors_.transpose();
  cv.topLeftCorner(p_, p_).noalias() = verrors_ * verrors_.transpose();
  c /= nv_;
  cv /= nv_;
  if (!c.allFinite() || !cv.allFinite()) return;
  const std::vector<double>& fading = Fading();
  const double d = Surprised(h, c) ? 1.0
                                   : fading[std::min(static_cast<std::size_t>(count_[h]), fading.size() - 1)];
  cov_[h] = (1.0 - d) * cov_[h] + d * c;
  cov_v_[h] = (1.0 - d) * cov_v_[h] + d * cv;
  count_[h] += 1.0;
  cached_[h] = false;
  var_cached_[h] = false;
}

void Combiner::Observe(const Vector& qpos, const Vector& qvel, const Vector& mean_qpos, const Vector& mean_qvel,
                       const Vector& act, const Vector& force, const std::optional<Vector>& rate) {
  RequireSize(qpos, nq_, "qpos");
  RequireSize(qvel, nv_, "qvel");
  RequireSize(mean_qpos, nq_, "mean_qpos");
  RequireSize(mean_qvel, nv_, "mean_qvel");
  RequireSize(act, na_, "act");
  RequireSize(force, nv_, "force");
  if (rate) RequireSize(*rate, nv_, "rate");
  // Only scoring probes score, oldest first; the last frame's probe was kept for a gap alone.
  for (int i = 0; i < n_; ++i) {
    const std::int64_t age = marks_[i][kAge];
    if (marks_[i][kKeep] == 1 && age >= 1 && age <= horizon_) Score(i, qpos, qvel);
  }
  int m = 0;
  for (int i = 0; i < n_; ++i) {
    if (marks_[i][kKeep] == 1 && marks_[i][kAge] < horizon_) {
      if (m != i) {
        marks_[m] = marks_[i];
        table_.row(m) = table_.row(i);
      }
      ++m;
    }
  }
  Vector& a0 = a0_;
  if (has_anchor_ && anchor_tick_ < tick_) {
    a0 = (qvel - anchor_v_) / (static_cast<double>(tick_ - anchor_tick_) * dt_);
  } else {
    a0.setZero();
  }
  // Only a frame that follows a frame of the tick before starts a scoring probe.
  const bool streak = has_anchor_ && anchor_tick_ == tick_ - 1;
  has_anchor_ = true;
  anchor_q_ = qpos;
  anchor_v_ = qvel;
  anchor_tick_ = tick_;
  const bool keep = streak && tick_ % stride_ == 0;
  matcher_.Record(tick_, qpos.data(), qvel.data());
  if (prior_) prior_->Record(tick_, qpos.data(), qvel.data());
  if (m + 1 > table_.rows()) Grow(2 * static_cast<int>(table_.rows()));
  auto row = table_.row(m);
  row.segment(c_.qpos, nq_) = mean_qpos.transpose();
  row.segment(c_.qvel, nv_) = mean_qvel.transpose();
  row.segment(c_.qacc, nv_).setZero();
  if (na_) row.segment(c_.act, na_) = act.transpose();
  row.segment(c_.force, nv_) = force.transpose();
  if (rate) {
    row.segment(c_.rate, nv_) = rate->transpose();
  } else {
    row.segment(c_.rate, nv_).setZero();
  }
  row.segment(c_.q0, nv_) = qpos.transpose();
  row.segment(c_.v0, nv_) = qvel.transpose();
  row.segment(c_.a0, nv_) = a0.transpose();
  marks_[m] = {tick_, 0, keep ? 1 : 0, rate ? 1 : 0, 0};
  n_ = m + 1;
  if (keep) MatchProbe(m);
}

PVector Combiner::SolveWeights(std::int64_t h, const PVector* scale, bool matched) const {
  PMatrix C = Weighing(h)[0];
  if (scale) C = (scale->asDiagonal() * C * scale->asDiagonal()).eval();
  // LEARNED weighs 0 until it has LEARNED_SAMPLES scores from real matches at h; with the prior's
  // scores, only the predictors they cover weigh until h has MIN_SAMPLES of the session's own;
  // PRIOR weighs 0 for a probe without a match of it.
  const bool learned = learned_count_[h] >= kLearnedSamples;
  std::array<int, kPredictors> allowed{};
  int k = 0;
  if (!prior_cov_.empty() && count_[h] < kMinSamples) {
    for (int p : kPriorBlock) allowed[k++] = p;
  } else if (matched && learned) {
    return MinVarianceWeights(C, p_);
  } else {
    for (int p = 0; p < p_; ++p) {
      if (learned || p != kLearned) allowed[k++] = p;
    }
  }
  if (!matched) k -= allowed[k - 1] == kPrior ? 1 : 0;
  return MinVarianceOver(C, allowed, k);
}

std::array<PMatrix, 2> Combiner::Weighing(std::int64_t h) const {
  if (prior_cov_.empty()) return {cov_[h], cov_v_[h]};
  // The prior's scores on other people's walking blended with the session's as a fading memory
  // holds a score made before the session's n, as far as the session's scores agree with them, at
  // the session's scale.
  const double share = PriorShare(count_[h]) * Agreement(cov_[h], count_[h]);
  const PMatrix C0 = AtScale(prior_cov_[h], cov_[h]), D0 = AtScale(prior_cov_v_[h], cov_v_[h]);
  std::array<PMatrix, 2> out = {cov_[h], cov_v_[h]};
  for (int i : kPriorBlock) {
    for (int j : kPriorBlock) {
      out[0](i, j) = share * C0(i, j) + (1.0 - share) * cov_[h](i, j);
      out[1](i, j) = share * D0(i, j) + (1.0 - share) * cov_v_[h](i, j);
    }
  }
  return out;
}

void Combiner::SetPriorScores(const std::vector<Eigen::Matrix4d>& cov, const std::vector<Eigen::Matrix4d>& cov_v) {
  if (cov.empty() && cov_v.empty()) return;
  Require(prior_ != nullptr, "the prior's scores need the prior");
  Require(cov.size() == static_cast<std::size_t>(horizon_ + 1) && cov_v.size() == cov.size(),
          "the prior's scores must have horizon + 1 = " + std::to_string(horizon_ + 1) + " covariances each, got " +
              std::to_string(cov.size()) + " and " + std::to_string(cov_v.size()));
  prior_cov_.assign(horizon_ + 1, PMatrix::Zero());
  prior_cov_v_.assign(horizon_ + 1, PMatrix::Zero());
  for (int h = 0; h <= horizon_; ++h) {
    for (int i = 0; i < 4; ++i) {
      for (int j = 0; j < 4; ++j) {
        prior_cov_[h](kPriorBlock[i], kPriorBlock[j]) = cov[h](i, j);
        prior_cov_v_[h](kPriorBlock[i], kPriorBlock[j]) = cov_v[h](i, j);
      }
    }
  }
}

std::optional<CombinedForecast> Combiner::Forecast(const std::optional<Vector>& noise_q,
                                                   const std::optional<Vector>& noise_qd, bool ended) {
  if (noise_q) RequireSize(*noise_q, nv_, "noise_q");
  if (noise_qd) RequireSize(*noise_qd, nv_, "noise_qd");
  const int i = n_ - 1;
  const std::int64_t last_origin = has_anchor_ ? anchor_tick_ : -1;
  if (i < 0 || marks_[i][kOrigin] != last_origin || marks_[i][kAge] == 0) return std::nullopt;
  // Past the scored horizon the filter answers, its prediction moving on.
  if (tick_ - marks_[i][kOrigin] - (ended ? 1 : 0) > horizon_) return std::nullopt;
  const std::int64_t h = std::min<std::int64_t>(marks_[i][kAge], horizon_);
  // The prior answers from the first tick: its scores are other people's.
  if (count_[h] < kMinSamples && !prior_) return std::nullopt;
  if (!marks_[i][kMatched]) MatchProbe(i);
  bool matched = !prior_;  // with the prior: whether a leg of it has a match
  for (int k = 0; prior_ && k < prior_->legs() * kPriorK; ++k) {
    matched = matched || !std::isnan(table_(i, c_.prior_rows + k));
  }
  PVector weights;
  if (!matched) {
    weights = SolveWeights(h, nullptr, false);
  } else {
    if (!cached_[h]) {
      weights_[h] = SolveWeights(h, nullptr);
      cached_[h] = true;
    }
    weights = weights_[h];
  }
  Predict(i);
  // The novelty guard: a predictor departing from the reference (STATIC moved towards
  // CONSTANT_ACCELERATION as far as the last two frames' velocities agree) by more than NOVELTY
  // times its scored past.
  const std::array<PMatrix, 2> weighing = Weighing(h);
  const PMatrix& C = weighing[0];
  const PMatrix& D = weighing[1];
  const auto row = table_.row(i);
  const double confirmed = Confirmed(row.segment(c_.v0, nv_), row.segment(c_.a0, nv_), dt_);
  PVector reference = PVector::Zero();
  reference[kStatic] = 1.0 - confirmed;
  reference[kAcceleration] += confirmed;
  at_.noalias() = pq_.transpose() * reference.head(p_);
  const PVector Cr = C * reference;
  const double rCr = reference.dot(Cr);
  PVector scale = PVector::Ones();
  bool novel = false;
  // Before SETTLED scores, on a motion the session scores unlike the prior's, a predictor that is the
  // reference's by r is judged by the rest, 1 - r.
  const bool settled = count_[h] >= kSettled || prior_cov_.empty() || Agreement(cov_[h], count_[h]) >= 1.0;
  for (int p = 0; p < p_; ++p) {
    if (p == kStatic) continue;
    const double now = (pq_.row(p) - at_.transpose()).squaredNorm() / nv_;
    const double limit = kNovelty * kNovelty * std::max(C(p, p) - 2.0 * Cr[p] + rCr, 0.0);
    if (now > limit) {
      novel = true;
      // The model's rollout takes the ratio's square.
      const double ratio = now / limit;
      scale[p] = std::min(p == kModel ? ratio : std::sqrt(ratio), kMaxNovelty);
      if (!settled) scale[p] = 1.0 + (1.0 - reference[p]) * (scale[p] - 1.0);
    }
  }
  CombinedForecast out;
  double var_q, var_qd;
  if (novel) {
    out.weights = SolveWeights(h, &scale, matched);
    const PMatrix S = scale * scale.transpose();
    var_q = out.weights.dot(S.cwiseProduct(C) * out.weights);
    var_qd = out.weights.dot(S.cwiseProduct(D) * out.weights);
  } else {
    // Kept with the weights until a score changes them (the first weights asked for since).
    out.weights = weights;
    if (!var_cached_[h]) {
      variances_[h] = {weights.dot(C * weights), weights.dot(D * weights)};
      var_cached_[h] = true;
    }
    var_q = variances_[h][0];
    var_qd = variances_[h][1];
  }
  out.qpos = pq_.transpose() * out.weights.head(p_);
  out.qvel = pv_.transpose() * out.weights.head(p_);
  out.qacc = pa_.transpose() * out.weights.head(p_);
  out.var_q = NetOfNoise(var_q, noise_q, nv_);
  out.var_qd = NetOfNoise(var_qd, noise_qd, nv_);
  return out;
}

std::int64_t Combiner::FillWindow(const Matrix& q, const Matrix& v) {
  Require(q.rows() == window() && q.cols() == nv_ && v.rows() == window() && v.cols() == nv_,
          "q and v must have shape (" + std::to_string(window()) + ", " + std::to_string(nv_) + ")");
  for (int k = 0; k < window(); ++k) {
    ++tick_;
    matcher_.Record(tick_, q.row(k).data(), v.row(k).data());
  }
  return tick_;
}

CombinerState Combiner::Snapshot() const {
  CombinerState s;
  s.tick = tick_;
  s.table = table_.topRows(n_);
  s.marks.assign(marks_.begin(), marks_.begin() + n_);
  s.cov = cov_;
  s.cov_v = cov_v_;
  s.count = count_;
  s.learned_count = learned_count_;
  s.has_anchor = has_anchor_;
  s.anchor_q = anchor_q_;
  s.anchor_v = anchor_v_;
  s.anchor_tick = anchor_tick_;
  s.learner = matcher_.State();
  if (prior_) s.prior = prior_->State();
  return s;
}

void Combiner::Restore(const CombinerState& s) {
  Require(s.table.cols() == c_.width && s.cov.size() == cov_.size(), "the snapshot is another combiner's");
  const int n = static_cast<int>(s.marks.size());
  if (n > table_.rows()) Grow(n);
  tick_ = s.tick;
  table_.topRows(n) = s.table;
  std::copy(s.marks.begin(), s.marks.end(), marks_.begin());
  n_ = n;
  cov_ = s.cov;
  cov_v_ = s.cov_v;
  count_ = s.count;
  learned_count_ = s.learned_count;
  has_anchor_ = s.has_anchor;
  anchor_q_ = s.anchor_q;
  anchor_v_ = s.anchor_v;
  anchor_tick_ = s.anchor_tick;
  matcher_.Restore(s.learner);
  if (prior_) prior_->Restore(s.prior);
  cached_.assign(horizon_ + 1, false);
  var_cached_.assign(horizon_ + 1, false);
}

}  // namespace jitdyn
