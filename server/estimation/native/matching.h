// Motion matching over a session's own frames, as server/estimation/matching.py's MotionMatcher does
// it, operation for operation (tests/server/test_native_forecast.py holds the two to 1e-9): a ring
// of the last frames indexed by tick, a feature (q at four lags and qd) every CANDIDATE_EVERY
// seconds, the K nearest candidates by the spread-scaled distance, and their continuation.
#ifndef JITDYN_SERVER_ESTIMATION_NATIVE_MATCHING_H_
#define JITDYN_SERVER_ESTIMATION_NATIVE_MATCHING_H_

#include <Eigen/Dense>

#include <array>
#include <cstdint>
#include <vector>

#include "ukf.h"

namespace jitdyn {

// matching.py's K, WINDOW, CANDIDATE_EVERY, LAG, FADE, REWIND_MARGIN.
constexpr int kMatchK = 10;

class MotionMatcher {
 public:
  MotionMatcher(int nv, double dt, int horizon);

  // The frame of `tick` (nv,) each; a tick recorded twice keeps the later frame.
  void Record(std::int64_t tick, const double* qpos, const double* qvel);
  // The K candidates most like the frame of `tick` into ticks and weights (K each); false when
  // there is no match (a hole within LAG before it, or too few candidates yet).
  bool Match(std::int64_t tick, double* ticks, double* weights);
  // qpos, qvel, qacc (nv,) of one match (ticks, weights: K each; ticks[0] NaN: no match, which
  // answers as CONSTANT_VELOCITY) `age` ticks on from the frame q0, v0.
  void Follow(const double* ticks, const double* weights, std::int64_t age, const double* q0, const double* v0,
              double* q, double* v, double* a) const;

  // The features' fading moments (2, features) flattened: the state beside the log.
  Vector State() const { return moments_; }
  void Restore(const Vector& state);
  int window() const { return window_; }

 private:
  // The feature of the frame of `tick` into out; false when a row of it is a hole.
  bool Feature(std::int64_t tick, double* out) const;
  std::int64_t Row(std::int64_t tick) const;  // tick modulo the capacity, as Python's %

  int nv_, horizon_, window_, capacity_, every_, slots_, width_;
  double dt_;
  std::array<int, 4> lags_;
  std::vector<std::int64_t> stamp_, cstamp_;
  Matrix q_, v_, a_, features_;
  Vector moments_;  // fading mean (width) then variance (width)
  Vector query_, inverse_, distance_;  // a match's scratch, sized once
  std::vector<int> order_;
};

}  // namespace jitdyn

#endif  // JITDYN_SERVER_ESTIMATION_NATIVE_MATCHING_H_
