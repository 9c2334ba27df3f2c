// IEEE 1278.1's dead-reckoning extrapolators (DIS's DRM F/R), written once for the native engine:
// the formulas of server/estimation/extrapolators.py's moved(), of one dof t seconds on from
// (q0, qd0, qdd0). The forecast's predictors (forecast.cc) and motion matching's fallback
// (matching.cc) call this.
#ifndef JITDYN_SERVER_ESTIMATION_NATIVE_EXTRAPOLATORS_H_
#define JITDYN_SERVER_ESTIMATION_NATIVE_EXTRAPOLATORS_H_

namespace jitdyn {

// In extrapolators.py's EXTRAPOLATORS order.
enum class Extrapolator { kStatic = 0, kConstantVelocity = 1, kConstantAcceleration = 2 };

inline void Extrapolate(Extrapolator kind, double q0, double qd0, double qdd0, double t, double* q, double* qd,
                        double* qdd) {
  switch (kind) {
    case Extrapolator::kStatic:
      *q = q0;
      *qd = qd0;
      *qdd = 0.0;
      return;
    case Extrapolator::kConstantVelocity:
      *q = q0 + qd0 * t;
      *qd = qd0;
      *qdd = 0.0;
      return;
    case Extrapolator::kConstantAcceleration:
      *q = q0 + (qd0 + 0.5 * t * qdd0) * t;
      *qd = qd0 + qdd0 * t;
      *qdd = qdd0;
      return;
  }
}

}  // namespace jitdyn

#endif  // JITDYN_SERVER_ESTIMATION_NATIVE_EXTRAPOLATORS_H_
