// See linearised.h. The order of operations follows server/estimation/linearised.py's PythonTick.
#include "linearised.h"

#include <Eigen/LU>

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace jitdyn {
namespace {

void Require(bool condition, const std::string& message) {
  if (!condition) throw std::invalid_argument(message);
}

}  // namespace

Ekf::Ekf(const mjModel* model, const mjModel* linearised, bool driven, int nstep, const Matrix& Q, const Matrix& R, double eps,
         double force_eps)
    : m_(model), linearised_(linearised), d_(nullptr), driven_(driven), nstep_(nstep), eps_(eps), force_eps_(force_eps), Q_(Q), R_(R) {
  Require(m_ != nullptr, "model must not be null");
  Require(linearised_ != nullptr && linearised_->opt.integrator != mjINT_RK4,
          "linearised must be a model mjd_transitionFD takes (not RK4)");
  Require(linearised_->nq == m_->nq && linearised_->nv == m_->nv && linearised_->na == m_->na,
          "linearised must be the process model's copy");
  nq_ = m_->nq;
  nv_ = m_->nv;
  na_ = m_->na;
  n_ = (driven_ ? 3 : 2) * nv_;
  Require(nstep_ >= 1, "nstep must be >= 1, got " + std::to_string(nstep_));
  Require(Q_.rows() == n_ && Q_.cols() == n_, "Q must have shape (" + std::to_string(n_) + ", " +
                                                  std::to_string(n_) + ")");
  Require(R_.rows() == 2 * nv_ && R_.cols() == 2 * nv_,
          "R must have shape (" + std::to_string(2 * nv_) + ", " + std::to_string(2 * nv_) + ")");
  d_ = mj_makeData(m_);
  Require(d_ != nullptr, "could not allocate mjData");
  jacobian_ = Matrix::Zero(2 * nv_ + na_, 2 * nv_ + na_);
}

Ekf::~Ekf() { mj_deleteData(d_); }

void Ekf::Set(const double* qpos, const double* qvel, const double* act, const double* qfrc) {
  d_->time = 0.0;
  mju_copy(d_->qpos, qpos, nq_);
  mju_copy(d_->qvel, qvel, nv_);
  if (na_) mju_copy(d_->act, act, na_);
  mju_copy(d_->qfrc_applied, qfrc, nv_);
}

void Ekf::Tangent(const double* qpos, const double* qvel, const double* qpos0, const double* qvel0,
                  double* out) const {
  mj_differentiatePos(m_, out, 1.0, qpos0, qpos);
  for (int i = 0; i < nv_; ++i) out[nv_ + i] = qvel[i] - qvel0[i];
}

void Ekf::Check(const Vector& x, const Matrix& P) const {
  int size = nq_ + n_ - nv_;
  Require(x.size() == size, "x must have " + std::to_string(size) + " entries, got " + std::to_string(x.size()));
  Require(P.rows() == n_ && P.cols() == n_, "P must have shape (" + std::to_string(n_) + ", " +
                                                std::to_string(n_) + "), got " + std::to_string(P.rows()) +
                                                " x " + std::to_string(P.cols()));
}

void Ekf::ForceColumns(Matrix& step, const Vector& qpos, const Vector& qvel, const Vector& act,
                       const Vector& force, const Vector& qpos1, const Vector& qvel1) {
  const int k = 2 * nv_;
  const bool rk4 = m_->opt.integrator == mjINT_RK4;
  Vector column(k);
  Set(qpos.data(), qvel.data(), act.data(), force.data());
  mj_forward(m_, d_);
  for (int i = 0; i < nv_; ++i) {
    double eps = force_eps_ * std::max(1.0, std::abs(force[i]));
    d_->qfrc_applied[i] = force[i] + eps;
    if (rk4) {
      mj_step(m_, d_);
    } else {
      mj_forwardSkip(m_, d_, mjSTAGE_VEL, 1);
      if (m_->opt.integrator == mjINT_EULER) {
        mj_Euler(m_, d_);
      } else {
        mj_implicit(m_, d_);
      }
    }
    Tangent(d_->qpos, d_->qvel, qpos1.data(), qvel1.data(), column.data());
    step.block(0, k + i, k, 1) = column / eps;
    Set(qpos.data(), qvel.data(), act.data(), force.data());
    if (rk4) mj_forward(m_, d_);
  }
}

std::tuple<Ekf::Vector, Ekf::Matrix, Ekf::Vector> Ekf::Predict(const Vector& x, const Matrix& P,
                                                               const Vector& act_in, const Vector& qfrc) {
  Check(x, P);
  Require(act_in.size() == na_, "act must have " + std::to_string(na_) + " entries, got " +
                                    std::to_string(act_in.size()));
  Require(qfrc.size() == nv_, "qfrc must have " + std::to_string(nv_) + " entries, got " +
                                  std::to_string(qfrc.size()));
  const int k = 2 * nv_;
  Vector qpos = x.head(nq_), qvel = x.segment(nq_, nv_), act = act_in;
  Vector force = driven_ ? Vector(x.tail(nv_)) : qfrc;
  Vector qpos1(nq_), qvel1(nv_), act1(na_);
  Matrix A = Matrix::Identity(n_, n_), step(n_, n_);
  for (int s = 0; s < nstep_; ++s) {
    step.setIdentity();
    Set(qpos.data(), qvel.data(), act.data(), force.data());
    mjd_transitionFD(linearised_, d_, eps_, 0, jacobian_.data(), nullptr, nullptr, nullptr);
    step.topLeftCorner(k, k) = jacobian_.topLeftCorner(k, k);
    Set(qpos.data(), qvel.data(), act.data(), force.data());
    mj_step(m_, d_);
    mju_copy(qpos1.data(), d_->qpos, nq_);
    mju_copy(qvel1.data(), d_->qvel, nv_);
    if (na_) mju_copy(act1.data(), d_->act, na_);
    if (driven_) ForceColumns(step, qpos, qvel, act, force, qpos1, qvel1);
    A = step * A;
    qpos = qpos1;
    qvel = qvel1;
    act = act1;
  }
  Vector out = x;
  out.head(nq_) = qpos;
  out.segment(nq_, nv_) = qvel;
  Matrix prior = A * P * A.transpose() + Q_;
  Matrix symmetric = 0.5 * (prior + prior.transpose());
  return {out, symmetric, act};
}

std::tuple<Ekf::Vector, Ekf::Matrix, double> Ekf::Update(const Vector& x, const Matrix& P, const Vector& z) {
  Check(x, P);
  Require(z.size() == nq_ + nv_, "z must have " + std::to_string(nq_ + nv_) + " entries, got " +
                                     std::to_string(z.size()));
  const int k = 2 * nv_;
  Matrix S = P.topLeftCorner(k, k) + R_;
  Eigen::PartialPivLU<Eigen::MatrixXd> lu(S);
  Matrix gain = lu.solve(Eigen::MatrixXd(P.topRows(k))).transpose();  // (n, 2 nv)
  Vector y(k);
  Tangent(z.data(), z.data() + nq_, x.data(), x.data() + nq_, y.data());
  double nis = y.dot(lu.solve(y));
  Matrix joseph = Matrix::Identity(n_, n_);
  joseph.leftCols(k) -= gain;
  Matrix posterior = joseph * P * joseph.transpose() + gain * R_ * gain.transpose();
  Vector dx = gain * y;
  Vector out = x;
  out.tail(n_ - nv_) += dx.tail(n_ - nv_);
  mj_integratePos(m_, out.data(), dx.data(), 1.0);
  return {out, posterior, nis};
}

}  // namespace jitdyn
