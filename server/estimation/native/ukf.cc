// See ukf.h. The order of operations follows server/estimation/fast.py line by line, so that the
// two agree to rounding (the tests hold them to 1e-9).
#include "ukf.h"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/LU>

#include <cfloat>
#include <cmath>
#include <limits>
#include <string>
#include <utility>

namespace jitdyn {
namespace {

// Eigenvalues of a repaired covariance are at least this fraction of the largest one (as
// server/estimation/sigma.py's _EIGEN_FLOOR).
constexpr double kEigenFloor = 1e-12;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// Where a component of an mjSTATE_FULLPHYSICS vector starts: components are laid out in bit order.
int StateOffset(const mjModel* m, int component) {
  int offset = 0;
  for (int bit = 0; (1 << bit) < component; ++bit) {
    if ((1 << bit) & mjSTATE_FULLPHYSICS) offset += mj_stateSize(m, 1 << bit);
  }
  return offset;
}

// The symmetric positive definite matrix nearest to A, up to the eigenvalue floor.
Eigen::MatrixXd NearestPositiveDefinite(const Eigen::MatrixXd& A) {
  Eigen::MatrixXd S = 0.5 * (A + A.transpose());
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eigen(S);
  Eigen::VectorXd values = eigen.eigenvalues();
  double top = values.size() ? values.cwiseAbs().maxCoeff() : 0.0;
  double floor = std::max(top * kEigenFloor, DBL_MIN);
  values = values.cwiseMax(floor);
  const Eigen::MatrixXd& V = eigen.eigenvectors();
  Eigen::MatrixXd R = (V * values.asDiagonal()) * V.transpose();
  return 0.5 * (R + R.transpose());
}

void Require(bool condition, const std::string& message) {
  if (!condition) throw std::invalid_argument(message);
}

}  // namespace

Ukf::Ukf(const mjModel* model, UkfSpec spec) : m_(model), d_(nullptr), spec_(std::move(spec)) {
  Require(m_ != nullptr, "model must not be null");
  nq_ = m_->nq;
  nv_ = m_->nv;
  na_ = m_->na;
  nu_ = m_->nu;
  const UkfSpec& s = spec_;
  manifold_ = nq_ != nv_;
  int order = s.controlled ? 3 : 2;
  Require(s.n == (order + s.fblocks) * nv_,
          "n must be " + std::to_string((order + s.fblocks) * nv_) + ", got " + std::to_string(s.n));
  Require(s.size == nq_ + s.n - nv_,
          "size must be " + std::to_string(nq_ + s.n - nv_) + ", got " + std::to_string(s.size));
  Require(s.wm.size() == s.wc.size() && s.wm.size() > 0, "wm and wc must be of one positive length");
  Require(s.nstep >= 1, "nstep must be >= 1, got " + std::to_string(s.nstep));
  for (int i : s.z_index) Require(0 <= i && i < s.size, "z_index out of range: " + std::to_string(i));
  for (int i = 0; i < nq_; ++i) {
    Require(static_cast<int>(s.z_index.size()) > i && s.z_index[i] == i, "z_index must start with qpos");
  }
  if (s.scheme == Scheme::kSimplex) {
    Require(s.unit.rows() == s.n && s.unit.cols() == s.n + 1, "unit must have shape (n, n + 1)");
  }
  d_ = mj_makeData(m_);
  Require(d_ != nullptr, "could not allocate mjData");
  template_.resize(mj_stateSize(m_, mjSTATE_FULLPHYSICS));
  mj_getState(m_, d_, template_.data(), mjSTATE_FULLPHYSICS);
  qpos_at_ = StateOffset(m_, mjSTATE_QPOS);
  qvel_at_ = StateOffset(m_, mjSTATE_QVEL);
  act_at_ = StateOffset(m_, mjSTATE_ACT);
  x = Vector::Zero(s.size);
  P = Matrix::Identity(s.n, s.n);
  Q = Matrix::Zero(s.n, s.n);
  const int z_tangent = static_cast<int>(s.z_index.size()) - nq_ + nv_;
  R = Matrix::Identity(z_tangent, z_tangent);
  act = Vector::Zero(na_);
  ctrl = Vector::Zero(nu_);
  qfrc = Vector::Zero(nv_);
  propagated_act = Vector::Zero(na_);
  sigmas_ = Matrix::Zero(nsigma(), s.size);
}

Ukf::~Ukf() {
  if (d_) mj_deleteData(d_);
}

Matrix Ukf::Add(const Vector& x0, const Matrix& dx) const {
  const int rows = static_cast<int>(dx.rows()), rest = static_cast<int>(x0.size()) - nq_;
  Matrix out(rows, x0.size());
  for (int i = 0; i < rows; ++i) {
    out.row(i) = x0.transpose();
    out.row(i).tail(rest) += dx.row(i).tail(rest);
    // In place, renormalising the quaternions (as manifold.py's add).
    mj_integratePos(m_, out.row(i).data(), dx.row(i).data(), 1.0);
  }
  return out;
}

Matrix Ukf::Residual(const Matrix& a, const Matrix& b) const {
  const int rows = static_cast<int>(std::max(a.rows(), b.rows()));
  const int rest = static_cast<int>(a.cols()) - nq_;
  Matrix out(rows, nv_ + rest);
  for (int i = 0; i < rows; ++i) {
    const auto ai = a.row(a.rows() > 1 ? i : 0);
    const auto bi = b.row(b.rows() > 1 ? i : 0);
    out.row(i).tail(rest) = ai.tail(rest) - bi.tail(rest);
    mj_differentiatePos(m_, out.row(i).data(), 1.0, bi.data(), ai.data());
  }
  return out;
}

Vector Ukf::Mean(const Matrix& points) const {
  // The Karcher mean of manifold.py: from the point of largest weight, its tangent step at most
  // kMeanIterations times, until the step is under kMeanTolerance.
  constexpr double kMeanTolerance = 1e-12;
  constexpr int kMeanIterations = 20;
  const Vector& w = spec_.wm;
  const int rest = static_cast<int>(points.cols()) - nq_;
  Eigen::Index top = 0;
  for (Eigen::Index i = 1; i < w.size(); ++i) {
    if (w[i] > w[top]) top = i;
  }
  Vector mean = points.row(top).transpose();
  mean.tail(rest) = points.rightCols(rest).transpose() * w;
  for (int iteration = 0; iteration < kMeanIterations; ++iteration) {
    Vector step = Residual(points, mean.transpose()).leftCols(nv_).transpose() * w;
    mj_integratePos(m_, mean.data(), step.data(), 1.0);
    if ((step.size() ? step.cwiseAbs().maxCoeff() : 0.0) < kMeanTolerance) break;
  }
  return mean;
}

Matrix Ukf::RobustCholeskyUpper(const Matrix& A) {
  const int n = static_cast<int>(A.rows());
  if (!A.allFinite()) return Matrix::Constant(n, n, kNaN);
  Eigen::MatrixXd a = A;
  // The upper triangle, as LAPACK's potrf(lower=0) reads it: U.T U = A.
  Eigen::LLT<Eigen::MatrixXd, Eigen::Upper> llt(a);
  if (llt.info() == Eigen::Success) return llt.matrixU();
  ++repairs_;
  Eigen::LLT<Eigen::MatrixXd, Eigen::Upper> repaired(NearestPositiveDefinite(a));
  if (repaired.info() == Eigen::Success) return repaired.matrixU();
  return Matrix::Constant(n, n, kNaN);
}

Matrix Ukf::SigmaPoints(const Vector& x0, const Matrix& P0) {
  const UkfSpec& s = spec_;
  Require(x0.size() == s.size, "x must have " + std::to_string(s.size) + " entries");
  Require(P0.rows() == s.n && P0.cols() == s.n, "P must be (n, n)");
  const int n = s.n;
  Matrix sigmas(nsigma(), s.size);
  if (s.scheme == Scheme::kSimplex) {
    Matrix U = RobustCholeskyUpper(P0);
    Matrix offsets = (U.transpose() * s.unit).transpose();  // (n + 1, n)
    if (manifold_) return Add(x0, offsets);
    for (int i = 0; i < n + 1; ++i) sigmas.row(i) = x0.transpose() + offsets.row(i);
    return sigmas;
  }
  Matrix U = RobustCholeskyUpper(s.scale * P0);
  if (manifold_) {
    Matrix plus = Add(x0, U), minus = Add(x0, -U);
    int first = s.scheme == Scheme::kMerwe ? 1 : 0;
    if (first) sigmas.row(0) = x0.transpose();
    sigmas.middleRows(first, n) = plus;
    sigmas.middleRows(first + n, n) = minus;
    return sigmas;
  }
  int first = 0;
  if (s.scheme == Scheme::kMerwe) {
    sigmas.row(0) = x0.transpose();
    first = 1;
  }
  for (int k = 0; k < n; ++k) {
    sigmas.row(first + k) = x0.transpose() + U.row(k);
    sigmas.row(first + n + k) = x0.transpose() - U.row(k);
  }
  return sigmas;
}

void Ukf::StepPoint(const double* row, double* out, double* act_out, int nstep, bool ramp) {
  std::vector<mjtNum>& state = template_;
  mju_copy(state.data() + qpos_at_, row, nq_);
  mju_copy(state.data() + qvel_at_, row + nq_, nv_);
  if (na_) mju_copy(state.data() + act_at_, act.data(), na_);
  mj_setState(m_, d_, state.data(), mjSTATE_FULLPHYSICS);
  if (nu_) {
    if (spec_.inputs == Inputs::kCtrl) {
      mju_copy(d_->ctrl, ctrl.data(), nu_);
    } else {
      mju_zero(d_->ctrl, nu_);
    }
  }
  const int fblocks = spec_.fblocks;
  if (fblocks > 0) {
    const double* force = row + nq_ + nv_;
    const double* rate = fblocks == 2 ? force + nv_ : nullptr;
    const double h = m_->opt.timestep;
    for (int step = 0; step < nstep; ++step) {
      if (ramp) {
        const double t = (step + 0.5) * h;
        for (int j = 0; j < nv_; ++j) d_->qfrc_applied[j] = force[j] + t * rate[j];
      } else if (step == 0) {
        mju_copy(d_->qfrc_applied, force, nv_);
      }
      mj_step(m_, d_);
    }
  } else {
    if (spec_.inputs == Inputs::kQfrc) {
      mju_copy(d_->qfrc_applied, qfrc.data(), nv_);
    } else {
      mju_zero(d_->qfrc_applied, nv_);
    }
    for (int step = 0; step < nstep; ++step) mj_step(m_, d_);
  }
  mju_copy(out, d_->qpos, nq_);
  mju_copy(out + nq_, d_->qvel, nv_);
  if (spec_.controlled) mju_copy(out + nq_ + nv_, d_->qacc, nv_);
  if (na_) mju_copy(act_out, d_->act, na_);
}

Matrix Ukf::Propagate(const Matrix& sigmas, int nstep) {
  Require(sigmas.cols() == spec_.size, "sigmas must have " + std::to_string(spec_.size) + " columns");
  Require(sigmas.rows() >= 1 && sigmas.rows() <= nsigma(),
          "sigmas must have 1 to " + std::to_string(nsigma()) + " rows");
  Require(nstep >= 1, "nstep must be >= 1, got " + std::to_string(nstep));
  const int count = static_cast<int>(sigmas.rows());
  const int head = nq_ + nv_;
  Matrix moved = sigmas;  // DRIVEN keeps each point's force (and rate)
  Matrix acts(count, na_);
  const bool ramp = spec_.fblocks == 2;
  for (int i = 0; i < count; ++i) {
    // CONTROLLED: qdd does not act, so a point equal to the first in (q, qd) moves as it does.
    if (spec_.controlled && i > 0 && (sigmas.row(i).head(head).array() == sigmas.row(0).head(head).array()).all()) {
      moved.row(i) = moved.row(0);
      if (na_) acts.row(i) = acts.row(0);
      continue;
    }
    StepPoint(sigmas.row(i).data(), moved.row(i).data(), na_ ? acts.row(i).data() : nullptr, nstep, ramp);
  }
  if (ramp) {
    const double span = nstep * m_->opt.timestep;
    moved.middleCols(head, nv_) += span * sigmas.middleCols(head + nv_, nv_);
  }
  if (na_) propagated_act = acts.transpose() * spec_.wm.head(count);
  return moved;
}

void Ukf::Predict() {
  Matrix sigmas = SigmaPoints(x, P);
  Matrix moved = Propagate(sigmas, spec_.nstep);
  Vector mean = manifold_ ? Mean(moved) : Vector(moved.transpose() * spec_.wm);
  Matrix spread = manifold_ ? Residual(moved, mean.transpose()) : Matrix(moved.rowwise() - mean.transpose());
  Matrix prior = spread.transpose() * (spec_.wc.asDiagonal() * spread);
  prior += Q;
  x = std::move(mean);
  P = std::move(prior);
  drawn_x_ = x;
  drawn_P_ = P;
  drawn_pending_ = true;
}

const Matrix& Ukf::sigmas_f() {
  if (drawn_pending_) {
    sigmas_ = SigmaPoints(drawn_x_, drawn_P_);
    drawn_pending_ = false;
  }
  return sigmas_;
}

void Ukf::set_sigmas_f(const Matrix& sigmas) {
  Require(sigmas.rows() == nsigma() && sigmas.cols() == spec_.size, "sigmas_f must be (nsigma, size)");
  drawn_pending_ = false;
  sigmas_ = sigmas;
}

void Ukf::Update(const Vector& z) {
  const int m = static_cast<int>(spec_.z_index.size());
  const int mt = m - nq_ + nv_;  // z's tangent dimension
  Require(z.size() == m, "z must have " + std::to_string(m) + " entries, got " + std::to_string(z.size()));
  Require(R.rows() == mt && R.cols() == mt, "R must be (dim_z, dim_z) in z's tangent space");
  const Matrix& sf = sigmas_f();
  const int ns = nsigma();
  Matrix sh(ns, m);
  for (int j = 0; j < m; ++j) sh.col(j) = sf.col(spec_.z_index[j]);
  Vector zp = manifold_ ? Mean(sh) : Vector(sh.transpose() * spec_.wm);
  Matrix dz = manifold_ ? Residual(sh, zp.transpose()) : Matrix(sh.rowwise() - zp.transpose());
  Matrix weighted = spec_.wc.asDiagonal() * dz;
  Matrix innovation_cov = dz.transpose() * weighted;
  innovation_cov += R;
  Matrix dx = manifold_ ? Residual(sf, x.transpose()) : Matrix(sf.rowwise() - x.transpose());
  const Eigen::MatrixXd square = innovation_cov;
  Eigen::PartialPivLU<Eigen::MatrixXd> lu(square);
  if ((lu.matrixLU().diagonal().array() == 0.0).any()) throw SingularMatrix("Singular matrix");
  Matrix inverse = lu.inverse();
  Matrix cross = dx.transpose() * weighted;
  Matrix gain = cross * inverse;
  Vector innovation = manifold_ ? Vector(Residual(z.transpose(), zp.transpose()).row(0).transpose()) : Vector(z - zp);
  x = manifold_ ? Vector(Add(x, (gain * innovation).transpose()).row(0).transpose()) : Vector(x + gain * innovation);
  P = P - gain * (innovation_cov * gain.transpose());
  nis = (innovation.transpose() * inverse).dot(innovation);
  S = std::move(innovation_cov);
  SI = std::move(inverse);
  K = std::move(gain);
  y = std::move(innovation);
}

bool Ukf::Tidy() {
  if (!x.allFinite() || !P.allFinite()) return false;
  Matrix symmetric = 0.5 * (P + P.transpose());
  Eigen::LLT<Eigen::MatrixXd, Eigen::Upper> llt(symmetric);
  if (llt.info() == Eigen::Success) {
    P = std::move(symmetric);
  } else {
    ++repairs_;
    P = NearestPositiveDefinite(symmetric);
  }
  return true;
}

Vector Ukf::Forward(const Vector& qpos, const Vector& qvel, const Vector& act_at, const Vector& ctrl_at,
                    const Vector& qfrc_at) {
  Require(qpos.size() == nq_ && qvel.size() == nv_ && act_at.size() == na_ && ctrl_at.size() == nu_ &&
              qfrc_at.size() == nv_,
          "forward needs qpos (nq,), qvel (nv,), act (na,), ctrl (nu,) and qfrc (nv,)");
  mju_copy(d_->qpos, qpos.data(), nq_);
  mju_copy(d_->qvel, qvel.data(), nv_);
  if (na_) mju_copy(d_->act, act_at.data(), na_);
  if (nu_) mju_copy(d_->ctrl, ctrl_at.data(), nu_);
  mju_copy(d_->qfrc_applied, qfrc_at.data(), nv_);
  mj_forward(m_, d_);
  return Eigen::Map<const Vector>(d_->qacc, nv_);
}

}  // namespace jitdyn
