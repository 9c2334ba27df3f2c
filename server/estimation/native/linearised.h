// jitdyn's linearised filter (an EKF) on MuJoCo's C API: a tick's mean by mj_step, its Jacobian by
// mjd_transitionFD (and, in DRIVEN, the held force's columns by forward differences of the step),
// P = A P A' + Q, and the update of [qpos, qvel] in Joseph's form. The same maths, in the same
// order, as server/estimation/linearised.py's PythonTick, which the tests hold this to
// (tests/server/test_linearised.py). Stateless between calls but for scratch: the caller holds
// x, P and the inputs, so that snapshots are the caller's. One thread at a time.
#ifndef JITDYN_SERVER_ESTIMATION_NATIVE_LINEARISED_H_
#define JITDYN_SERVER_ESTIMATION_NATIVE_LINEARISED_H_

#include <Eigen/Dense>
#include <mujoco/mujoco.h>

#include <tuple>

namespace jitdyn {

class Ekf {
 public:
  using Matrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
  using Vector = Eigen::VectorXd;

  // model: the EKF's process model, linearised: what mjd_transitionFD differentiates (the same, or
  // its Euler copy for RK4), both kept alive by the caller; nstep: its steps a tick; driven:
  // x = [qpos, qvel, f], else [qpos, qvel]; Q (n, n), R (2 nv, 2 nv); eps: mjd_transitionFD's;
  // force_eps: the force columns' (times max(1, |f_i|)).
  Ekf(const mjModel* model, const mjModel* linearised, bool driven, int nstep, const Matrix& Q, const Matrix& R, double eps,
      double force_eps);
  ~Ekf();
  Ekf(const Ekf&) = delete;
  Ekf& operator=(const Ekf&) = delete;

  // (x, P, act) a tick on; qfrc (nv,) the force held over it (unused in DRIVEN).
  std::tuple<Vector, Matrix, Vector> Predict(const Vector& x, const Matrix& P, const Vector& act,
                                             const Vector& qfrc);
  // (x, P, NIS) after the frame z = [qpos, qvel]; throws std::invalid_argument on shapes.
  std::tuple<Vector, Matrix, double> Update(const Vector& x, const Matrix& P, const Vector& z);

  int n() const { return n_; }

 private:
  void Set(const double* qpos, const double* qvel, const double* act, const double* qfrc);
  // [qpos (-) qpos0, qvel - qvel0] into out (2 nv).
  void Tangent(const double* qpos, const double* qvel, const double* qpos0, const double* qvel0,
               double* out) const;
  void Check(const Vector& x, const Matrix& P) const;
  // step's force columns: forward differences of the step from (qpos, qvel, act) under force in
  // each force component, against the nominal step's (qpos1, qvel1). The position and velocity
  // stages run once; each column runs the acceleration stage and the integrator (RK4: a step).
  void ForceColumns(Matrix& step, const Vector& qpos, const Vector& qvel, const Vector& act,
                    const Vector& force, const Vector& qpos1, const Vector& qvel1);

  const mjModel* m_;
  const mjModel* linearised_;
  mjData* d_;
  bool driven_;
  int nstep_, nq_, nv_, na_, n_;
  double eps_, force_eps_;
  Matrix Q_, R_;
  Matrix jacobian_;  // (2 nv + na)^2, mjd_transitionFD's A
};

}  // namespace jitdyn

#endif  // JITDYN_SERVER_ESTIMATION_NATIVE_LINEARISED_H_
