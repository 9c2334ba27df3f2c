// jitdyn's unscented Kalman filter on MuJoCo's C API: sigma points, their propagation through
// mj_step on one mjData, the unscented transform and the update, with the session's filter
// state held here. The same maths, in the same order, as server/estimation/fast.py, which the
// tests hold this to (tests/server/test_native.py). One instance per session, one thread at a time.
#ifndef JITDYN_SERVER_ESTIMATION_NATIVE_UKF_H_
#define JITDYN_SERVER_ESTIMATION_NATIVE_UKF_H_

#include <Eigen/Dense>
#include <mujoco/mujoco.h>

#include <stdexcept>
#include <vector>

namespace jitdyn {

using Matrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using Vector = Eigen::VectorXd;

enum class Scheme { kMerwe = 0, kSimplex = 1, kUniform = 2 };
enum class Inputs { kNone = 0, kCtrl = 1, kQfrc = 2 };

// An innovation covariance that cannot be inverted (numpy's LinAlgError on the Python side).
class SingularMatrix : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// What fixes a filter for its whole life; checked by the constructor.
struct UkfSpec {
  int n = 0;                  // tangent dimension (side of P)
  int size = 0;               // len(x): nq + n - nv
  int fblocks = 0;            // DRIVEN: 1 (force) or 2 (force and its rate); else 0
  bool controlled = false;    // x = [q, qd, qdd], qdd the last step's qacc
  Scheme scheme = Scheme::kMerwe;
  double scale = 1.0;         // Merwe: n + lambda; uniform: n alpha^2 (simplex: unused)
  Matrix unit;                // simplex: (n, n + 1) offsets of a unit covariance
  Vector wm, wc;              // (nsigma,) weights
  std::vector<int> z_index;   // measured entries of x
  int nstep = 1;              // physics steps per tick
  Inputs inputs = Inputs::kNone;
};

class Ukf {
 public:
  Ukf(const mjModel* model, UkfSpec spec);
  ~Ukf();
  Ukf(const Ukf&) = delete;
  Ukf& operator=(const Ukf&) = delete;

  // x, P <- the unscented transform of the propagated sigma points of (x, P), plus Q.
  void Predict();
  // The unscented update with measurement z (dim_z,); throws SingularMatrix.
  void Update(const Vector& z);
  // The sigma points of (x, P) (nsigma, size); counts a repaired covariance in repairs().
  Matrix SigmaPoints(const Vector& x, const Matrix& P);
  // The process model on a sigma set (count, size), nstep physics steps; also sets
  // propagated_act to the weighted mean of the points' activations.
  Matrix Propagate(const Matrix& sigmas, int nstep);

  // x and P finite? Then P symmetrised, and repaired when indefinite (counted in repairs()).
  bool Tidy();
  // The largest diagonal entry of P.
  double LargestVariance() const { return P.diagonal().maxCoeff(); }
  // qacc (nv,) at (qpos, qvel, act) under ctrl and qfrc_applied: mj_forward on this filter's mjData.
  Vector Forward(const Vector& qpos, const Vector& qvel, const Vector& act_at, const Vector& ctrl_at,
                 const Vector& qfrc_at);

  // The update's points: drawn from the prior when first asked for after a predict.
  const Matrix& sigmas_f();
  void set_sigmas_f(const Matrix& sigmas);

  int nsigma() const { return static_cast<int>(spec_.wm.size()); }
  const UkfSpec& spec() const { return spec_; }
  int repairs() const { return repairs_; }
  void set_repairs(int repairs) { repairs_ = repairs; }

  // The filter's state and the inputs of its process model; read and written from Python.
  Vector x;
  Matrix P, Q, R;
  Vector act, ctrl, qfrc;
  // What the last update computed (filterpy's names).
  Vector y;
  Matrix K, S, SI;
  double nis = 0.0;  // y' SI y of the last update
  Vector propagated_act;

 private:
  // x (or z) moved along tangent rows dx; rows of points less rows of b as tangent vectors; the
  // weighted mean of points. `rest`: the entries after qpos (a state's, or a measurement's).
  Matrix Add(const Vector& x, const Matrix& dx) const;
  Matrix Residual(const Matrix& a, const Matrix& b) const;
  Vector Mean(const Matrix& points) const;
  Matrix RobustCholeskyUpper(const Matrix& A);
  void StepPoint(const double* row, double* out, double* act_out, int nstep, bool ramp);

  const mjModel* m_;
  mjData* d_;
  UkfSpec spec_;
  int nq_, nv_, na_, nu_;
  bool manifold_;  // ball or free joints: nq != nv
  std::vector<mjtNum> template_;  // a fresh mjData's FULLPHYSICS state: time 0, history, plugins
  int qpos_at_, qvel_at_, act_at_;
  int repairs_ = 0;
  bool drawn_pending_ = false;
  Vector drawn_x_;
  Matrix drawn_P_;
  Matrix sigmas_;
};

}  // namespace jitdyn

#endif  // JITDYN_SERVER_ESTIMATION_NATIVE_UKF_H_
