// The prior of human motion's predictor, as server/estimation/prior.py's PriorMatcher computes it
// (tests/server/test_native_forecast.py holds the two to 1e-9): a ring of the session's last frames,
// each leg's feature (its joints' angle changes over LAGS and velocity, scaled by the library's
// spread), the K library moments nearest to it among the candidates, and their continuation.
// The library's arrays come from Python once (a PriorTable per leg's joints, shared by sessions).
#ifndef JITDYN_SERVER_ESTIMATION_NATIVE_PRIOR_H_
#define JITDYN_SERVER_ESTIMATION_NATIVE_PRIOR_H_

#include <Eigen/Dense>

#include <array>
#include <cstdint>
#include <memory>
#include <vector>

#include "ukf.h"

namespace jitdyn {

// prior.py's K and the number of its LAGS.
constexpr int kPriorK = 10;
constexpr int kPriorLags = 3;

// One choice of the library's joints (prior.py's PriorLibrary.columns and index): q and qd of every
// row over them (N, J), each row's clip's last row (N,), the candidates (C,) and their scaled
// features (C, 4 J, joint by joint: the lags' changes, then the velocity term), the spreads (4 J).
struct PriorTable {
  double rate = 0.0;
  Matrix q, v;
  std::vector<std::int64_t> last, rows;
  Matrix features;
  Vector spread;
  int joints() const { return static_cast<int>(q.cols()); }
};

// A session's leg: its table and, per joint of it, the session's dof and its sign.
struct PriorLeg {
  std::shared_ptr<const PriorTable> table;
  std::vector<int> dofs;
  std::vector<double> signs;
};

// The ring of recent frames a match reads, for a snapshot.
struct PriorRing {
  std::vector<std::int64_t> stamp;
  Matrix q, v;
};

class PriorMatcher {
 public:
  PriorMatcher(std::vector<PriorLeg> legs, int nv, double dt);

  int legs() const { return static_cast<int>(legs_.size()); }
  void Record(std::int64_t tick, const double* qpos, const double* qvel);
  // Each leg's match for the frame of `tick` into rows and weights (legs x K each, leg by leg);
  // rows NaN (weights 0) where the frame is not recorded or is unlike any the library holds.
  void Match(std::int64_t tick, double* rows, double* weights);
  // qpos, qvel, qacc (nv,) `age` ticks on from the frame (q0, v0, a0) of one probe's matches: each
  // leg's dofs from its match, the others left as they come in (the fallback).
  void Follow(const double* rows, const double* weights, std::int64_t age, const double* q0, const double* v0,
              const double* a0, double* q, double* v, double* a) const;

  PriorRing State() const { return ring_; }
  void Restore(const PriorRing& ring);

 private:
  std::int64_t Row(std::int64_t tick) const;  // tick modulo the ring, as Python's %
  // The K nearest candidates of `table` to query over the components `kept` (count n), sorted:
  // their indices and squared distances.
  void Nearest(const PriorTable& table, int n);

  std::vector<PriorLeg> legs_;
  int nv_;
  double dt_;
  std::array<int, kPriorLags> lags_;
  PriorRing ring_;
  // A match's scratch, sized once.
  std::vector<double> query_;
  std::vector<int> kept_;
  std::array<int, kPriorK> found_;
  std::array<double, kPriorK> distance_;
};

}  // namespace jitdyn

#endif  // JITDYN_SERVER_ESTIMATION_NATIVE_PRIOR_H_
