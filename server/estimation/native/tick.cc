// One tick of a session's UKF in one call: tick.h says what it runs, estimation/ukf.py is the
// order it is held to (tests/server/test_native_tick.py: the same numbers as the separate calls).
#include "tick.h"

#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace jitdyn {

Tick::Tick(Ukf* ukf, Adapter* adapter, Combiner* combiner, TickSpec spec)
    : ukf_(ukf), adapter_(adapter), combiner_(combiner), spec_(std::move(spec)) {
  if (ukf_ == nullptr) throw std::invalid_argument("a Tick needs its Ukf");
  const long na = ukf_->act.size();
  if (spec_.act_low.size() != na || spec_.act_high.size() != na) {
    throw std::invalid_argument("act_low and act_high must have na = " + std::to_string(na) + " entries, got " +
                                std::to_string(spec_.act_low.size()) + " and " +
                                std::to_string(spec_.act_high.size()));
  }
  nv_ = static_cast<int>(ukf_->qfrc.size());
  nq_ = ukf_->spec().size - (ukf_->spec().n - nv_);
}

void Tick::ClipAct() {
  // np.clip's order: a NaN stays NaN.
  Vector act = ukf_->propagated_act;
  for (Eigen::Index i = 0; i < act.size(); ++i) {
    if (act[i] < spec_.act_low[i]) act[i] = spec_.act_low[i];
    if (act[i] > spec_.act_high[i]) act[i] = spec_.act_high[i];
  }
  ukf_->act = act;
}

TickPrediction Tick::Advance(bool gap) {
  if (adapter_ != nullptr) {
    ukf_->Q = adapter_->QFor(adapter_->q0());
    if (gap) ukf_->Q = adapter_->GapInflation() * ukf_->Q;
  }
  if (combiner_ != nullptr) combiner_->Advance();
  ukf_->Predict();
  ClipAct();
  TickPrediction out;
  out.finite = ukf_->Tidy();
  out.largest_variance = ukf_->LargestVariance();
  out.diverged = !out.finite || out.largest_variance > spec_.covariance_limit;
  return out;
}

TickUpdate Tick::Step(const Vector& z, bool quiet, const std::optional<Vector>& qvel) {
  TickUpdate out;
  out.prediction = Advance(false);
  if (out.prediction.diverged) return out;
  out.updated = true;
  if (adapter_ != nullptr) ukf_->R = adapter_->r().asDiagonal();
  // core.py correct: a singular S leaves nothing of the update usable.
  try {
    ukf_->Update(z);
    out.nis = ukf_->nis;
  } catch (const SingularMatrix&) {
    ukf_->x = Vector::Constant(ukf_->spec().size, std::numeric_limits<double>::quiet_NaN());
    out.nis = std::numeric_limits<double>::quiet_NaN();
  }
  if (!std::isfinite(out.nis)) out.nis = std::numeric_limits<double>::quiet_NaN();
  out.finite = ukf_->Tidy();
  out.largest_variance = ukf_->LargestVariance();
  // adaptive_steps.py adapt: an on-time frame is a consecutive one.
  if (adapter_ != nullptr && out.finite && !std::isnan(out.nis)) {
    const double m = static_cast<double>(ukf_->R.rows());
    // Contiguous copies: Eigen's packet sum, which orders the terms as numpy's dot does.
    const Vector si = ukf_->SI.diagonal(), r = ukf_->R.diagonal();
    const double share = si.dot(r) / m;
    auto verdict = adapter_->Observe(ukf_->y, true, ukf_->K, out.nis, share);
    out.observed = true;
    out.adapted = verdict.first;
    out.absorb = verdict.second;
  }
  const Vector& x = ukf_->x;
  if (spec_.force != TickForce::kNone) {
    out.has_qacc = true;
    if (x.allFinite()) {
      Vector ctrl = Vector::Zero(ukf_->ctrl.size());
      Vector force = spec_.force == TickForce::kState ? Vector(x.segment(nq_ + nv_, nv_)) : Vector::Zero(nv_);
      out.qacc = ukf_->Forward(x.head(nq_), x.segment(nq_, nv_), ukf_->act, ctrl, force);
    } else {
      out.qacc = Vector::Constant(nv_, std::numeric_limits<double>::quiet_NaN());
    }
  }
  // foresight.py observe, where no restart can follow this update (ukf.py _stepped).
  const bool kept = out.finite && out.largest_variance <= spec_.covariance_limit && !out.absorb;
  if (combiner_ != nullptr && quiet && kept && x.allFinite()) {
    const int fblocks = ukf_->spec().fblocks;
    std::optional<Vector> rate;
    if (fblocks == 2) rate = x.segment(nq_ + 2 * nv_, nv_);
    combiner_->Observe(z.head(nq_), qvel ? *qvel : Vector(x.segment(nq_, nv_)), x.head(nq_), x.segment(nq_, nv_),
                       ukf_->act, x.segment(nq_ + nv_, nv_), rate);
    out.observed_frame = true;
  }
  return out;
}

std::size_t TickState::Bytes() const {
  std::size_t doubles = x.size() + P.size() + sigmas_f.size();
  if (adapter) {
    const AdapterState& a = *adapter;
    doubles += a.r.size() + a.q_est.size() + a.nis.size() + a.d4.size() + a.reported_r.size() + a.reported_s.size();
    for (const Eigen::VectorXd& v : a.recent) doubles += v.size();
  }
  return doubles * sizeof(double) + (combiner ? combiner->Bytes() : 0);
}

TickState Tick::Snapshot() {
  TickState state;
  state.sigmas_f = ukf_->sigmas_f();
  state.x = ukf_->x;
  state.P = ukf_->P;
  if (adapter_ != nullptr) state.adapter = adapter_->state();
  if (combiner_ != nullptr) state.combiner = combiner_->Snapshot();
  return state;
}

void Tick::Restore(const TickState& state) {
  if (state.adapter.has_value() != (adapter_ != nullptr) || state.combiner.has_value() != (combiner_ != nullptr) ||
      state.x.size() != ukf_->x.size() || state.P.rows() != ukf_->P.rows()) {
    throw std::invalid_argument("a TickState of another filter");
  }
  ukf_->x = state.x;
  ukf_->P = state.P;
  ukf_->set_sigmas_f(state.sigmas_f);
  if (adapter_ != nullptr) adapter_->Restore(*state.adapter);
  if (combiner_ != nullptr) combiner_->Restore(*state.combiner);
}

}  // namespace jitdyn
