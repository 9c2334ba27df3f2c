// One tick of a session's UKF in one call (server/estimation/ukf.py's steps, in its order): the
// process noise of the tick, the forecast combination's advance, predict, the activations'
// clip, tidy; with a frame on time also the noise of the update, the update, tidy, the adaptive
// noise's observation, the estimate's forward dynamics and the combiner's observation of the
// frame; and the timewarp's snapshot of all of it in one copy. The guard's bookkeeping, restarts,
// absorptions and a gap's answers stay in Python (docs/decisions/0212-one-native-call-a-tick.md).
// Holds pointers to the session's Ukf, Adapter and Combiner, which the Python objects own.
#ifndef JITDYN_SERVER_ESTIMATION_NATIVE_TICK_H_
#define JITDYN_SERVER_ESTIMATION_NATIVE_TICK_H_

#include "adaptive.h"
#include "forecast.h"
#include "ukf.h"

#include <optional>

namespace jitdyn {

// What the estimate's qacc is computed under: none (CONTROLLED: qacc is in x; EXTERNAL: the
// restored force is Python's), no force (PASSIVE), or x's force block (DRIVEN).
enum class TickForce { kNone = 0, kZero = 1, kState = 2 };

// What the fixed parts of a tick are; checked by the constructor.
struct TickSpec {
  Vector act_low, act_high;     // (na,) the activations' bounds (answer.py activation_bounds)
  double covariance_limit = 0;  // guard.py COVARIANCE_LIMIT: a larger variance is a divergence
  TickForce force = TickForce::kNone;
};

// Everything of the filter's numbers a timewarp snapshot holds: x, P, the update's sigma points,
// the adapter's and the combiner's states. Opaque to Python, which reads its size.
struct TickState {
  Vector x;
  Matrix P, sigmas_f;
  std::optional<AdapterState> adapter;
  std::optional<CombinerState> combiner;
  std::size_t Bytes() const;
};

struct TickPrediction {
  bool finite = false;            // x and P finite after tidy
  double largest_variance = 0.0;  // P's largest diagonal entry (NaN when not finite)
  bool diverged = true;           // not finite, or a variance past the limit
};

struct TickUpdate {
  TickPrediction prediction;
  bool updated = false;      // false: the prediction diverged, nothing more was done
  bool finite = false;       // x and P finite after the update's tidy
  double nis = 0.0;          // NaN: not finite (or S singular: x is NaN)
  double largest_variance = 0.0;
  bool observed = false;     // the adapter observed this update
  bool adapted = false, absorb = false;
  bool has_qacc = false;     // qacc below is the estimate's (TickForce not kNone)
  Vector qacc;
  bool observed_frame = false;  // the combiner observed the frame and the posterior
};

class Tick {
 public:
  // adapter and combiner may be null; all three outlive this Tick.
  Tick(Ukf* ukf, Adapter* adapter, Combiner* combiner, TickSpec spec);

  // A tick's prediction; gap: a tick after one without its frame (the adapter's gap Q).
  TickPrediction Advance(bool gap);
  // An on-time tick: Advance(false), then, unless it diverged, the update with z (dim_z,). Then
  // the combiner observes the frame (qpos: z's head; qvel, or x's when empty) when `quiet` (the
  // guard's runs cannot restart the filter on this update) and x and P are no divergence and
  // were not absorbed: the cases in which Python would keep this posterior.
  TickUpdate Step(const Vector& z, bool quiet, const std::optional<Vector>& qvel);

  // The whole numeric state, in one copy, and back (the sigma points drawn first, as a read of
  // sigmas_f draws them).
  TickState Snapshot();
  void Restore(const TickState& state);

  // The filter as the last call left it: activations (na,), x (size,), P (n, n).
  const Vector& act() const { return ukf_->act; }
  const Vector& x() const { return ukf_->x; }
  const Matrix& P() const { return ukf_->P; }

 private:
  void ClipAct();

  Ukf* ukf_;
  Adapter* adapter_;
  Combiner* combiner_;
  TickSpec spec_;
  int nq_, nv_;
};

}  // namespace jitdyn

#endif  // JITDYN_SERVER_ESTIMATION_NATIVE_TICK_H_
