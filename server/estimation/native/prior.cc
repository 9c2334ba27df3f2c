// See prior.h. Mirrors server/estimation/prior.py's PriorMatcher (match, follow_library). Python
// queries a k-d tree; here each match is one pass over the leg's candidates, whose distance is
// summed as the tree sums it (four running sums, then the rest), so that the same K are chosen.
#include "prior.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

namespace jitdyn {
namespace {

// prior.py's LAGS (s), FEATURE_TIME (s), FADE (s), FARTHEST.
constexpr std::array<double, kPriorLags> kLags = {0.05, 0.10, 0.15};
constexpr double kFeatureTime = 0.1;
constexpr double kFade = 0.1;
constexpr double kFarthest = 4.0;
constexpr int kComponents = kPriorLags + 1;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

}  // namespace

PriorMatcher::PriorMatcher(std::vector<PriorLeg> legs, int nv, double dt)
    : legs_(std::move(legs)), nv_(nv), dt_(dt) {
  if (legs_.empty() || !(dt > 0.0)) {
    throw std::invalid_argument("a prior matcher needs a leg and dt > 0, got " + std::to_string(legs_.size()) +
                                " legs, dt " + std::to_string(dt));
  }
  int widest = 0;
  for (const PriorLeg& leg : legs_) {
    const PriorTable& t = *leg.table;
    const int j = t.joints();
    const std::size_t rows = t.q.rows();
    if (static_cast<int>(leg.dofs.size()) != j || static_cast<int>(leg.signs.size()) != j || t.v.rows() != t.q.rows() ||
        t.v.cols() != j || t.last.size() != rows || t.features.cols() != kComponents * j ||
        static_cast<std::size_t>(t.features.rows()) != t.rows.size() || t.spread.size() != kComponents * j ||
        t.rows.size() < static_cast<std::size_t>(kPriorK)) {
      throw std::invalid_argument("a prior leg's table, dofs and signs disagree in their sizes");
    }
    for (std::int64_t r : t.rows) {
      if (r < 0 || r >= static_cast<std::int64_t>(rows)) {
        throw std::invalid_argument("a prior table's candidate row " + std::to_string(r) + " is not one of its " +
                                    std::to_string(rows) + " rows");
      }
    }
    for (std::int64_t r : t.last) {
      if (r < 0 || r >= static_cast<std::int64_t>(rows)) {
        throw std::invalid_argument("a prior table's clip end " + std::to_string(r) + " is not one of its " +
                                    std::to_string(rows) + " rows");
      }
    }
    for (int dof : leg.dofs) {
      if (dof < 0 || dof >= nv) {
        throw std::invalid_argument("a prior leg's dof must be in [0, " + std::to_string(nv) + "), got " +
                                    std::to_string(dof));
      }
    }
    widest = std::max(widest, kComponents * j);
  }
  int longest = 0;
  for (int i = 0; i < kPriorLags; ++i) {
    lags_[i] = std::max(1, static_cast<int>(std::nearbyint(kLags[i] / dt)));  // Python's round: half to even
    longest = std::max(longest, lags_[i]);
  }
  ring_.stamp.assign(longest + 1, -1);
  ring_.q = Matrix::Zero(longest + 1, nv);
  ring_.v = Matrix::Zero(longest + 1, nv);
  query_.resize(widest);
  kept_.resize(widest);
}

std::int64_t PriorMatcher::Row(std::int64_t tick) const {
  const std::int64_t n = static_cast<std::int64_t>(ring_.stamp.size());
  return ((tick % n) + n) % n;
}

void PriorMatcher::Record(std::int64_t tick, const double* qpos, const double* qvel) {
  const std::int64_t row = Row(tick);
  ring_.stamp[row] = tick;
  for (int j = 0; j < nv_; ++j) {
    ring_.q(row, j) = qpos[j];
    ring_.v(row, j) = qvel[j];
  }
}

void PriorMatcher::Restore(const PriorRing& ring) {
  if (ring.stamp.size() != ring_.stamp.size() || ring.q.cols() != nv_) {
    throw std::invalid_argument("the snapshot is another prior's");
  }
  ring_ = ring;
}

void PriorMatcher::Nearest(const PriorTable& table, int n) {
  distance_.fill(std::numeric_limits<double>::infinity());
  found_.fill(-1);
  const int count = static_cast<int>(table.rows.size());
  const int width = static_cast<int>(table.features.cols());
  const double* data = table.features.data();
  for (int c = 0; c < count; ++c) {
    const double* f = data + static_cast<std::ptrdiff_t>(c) * width;
    // scipy's sqeuclidean_distance_double, over the components kept.
    // After each block of four, the running sums' total is at most the distance (sums of squares
    // only grow, in floating point too): a candidate already past the K-th nearest stops there.
    double acc[4] = {0.0, 0.0, 0.0, 0.0};
    int i = 0;
    bool beyond = false;
    for (; i + 4 <= n && !beyond; i += 4) {
      for (int r = 0; r < 4; ++r) {
        const double d = query_[i + r] - f[kept_[i + r]];
        acc[r] += d * d;
      }
      beyond = !(acc[0] + acc[1] + acc[2] + acc[3] < distance_[kPriorK - 1]);
    }
    if (beyond) continue;
    double s = acc[0] + acc[1] + acc[2] + acc[3];
    for (; i < n; ++i) {
      const double d = query_[i] - f[kept_[i]];
      s += d * d;
    }
    if (!(s < distance_[kPriorK - 1])) continue;
    int k = kPriorK - 1;
    for (; k > 0 && s < distance_[k - 1]; --k) {
      distance_[k] = distance_[k - 1];
      found_[k] = found_[k - 1];
    }
    distance_[k] = s;
    found_[k] = c;
  }
}

void PriorMatcher::Match(std::int64_t tick, double* rows, double* weights) {
  const int legs = this->legs();
  for (int k = 0; k < legs * kPriorK; ++k) {
    rows[k] = kNaN;
    weights[k] = 0.0;
  }
  const std::int64_t now = Row(tick);
  if (ring_.stamp[now] != tick) return;
  std::array<bool, kPriorLags> present;
  for (int l = 0; l < kPriorLags; ++l) present[l] = ring_.stamp[Row(tick - lags_[l])] == tick - lags_[l];
  for (int i = 0; i < legs; ++i) {
    const PriorLeg& leg = legs_[i];
    const PriorTable& table = *leg.table;
    int n = 0;
    for (std::size_t j = 0; j < leg.dofs.size(); ++j) {
      const int dof = leg.dofs[j];
      const double sign = leg.signs[j];
      for (int l = 0; l < kPriorLags; ++l) {
        if (!present[l]) continue;
        const double change = (ring_.q(Row(tick - lags_[l]), dof) - ring_.q(now, dof)) * sign;
        kept_[n] = kComponents * static_cast<int>(j) + l;
        query_[n] = change / table.spread[kept_[n]];
        ++n;
      }
      kept_[n] = kComponents * static_cast<int>(j) + kPriorLags;
      query_[n] = ring_.v(now, dof) * sign * kFeatureTime / table.spread[kept_[n]];
      ++n;
    }
    Nearest(table, n);
    // The tree's distances are square roots, squared again by prior.py.
    std::array<double, kPriorK> d, w;
    for (int k = 0; k < kPriorK; ++k) {
      const double root = std::sqrt(distance_[k]);
      d[k] = root * root;
    }
    if (!(d[0] <= kFarthest * n)) continue;
    double total = 0.0;
    for (int k = 0; k < kPriorK; ++k) {
      w[k] = 1.0 / (d[k] + 1e-3 * d[0] + 1e-12);
      total += w[k];
    }
    for (int k = 0; k < kPriorK; ++k) {
      rows[i * kPriorK + k] = static_cast<double>(table.rows[found_[k]]);
      weights[i * kPriorK + k] = w[k] / total;
    }
  }
}

void PriorMatcher::Follow(const double* rows, const double* weights, std::int64_t age, const double* q0,
                          const double* v0, const double* a0, double* q, double* v, double* a) const {
  const double t = static_cast<double>(age) * dt_;
  const double u = t / kFade;
  const double fade = std::exp(-u);
  for (int i = 0; i < legs(); ++i) {
    const PriorLeg& leg = legs_[i];
    const PriorTable& table = *leg.table;
    const double* r = rows + i * kPriorK;
    const double* wk = weights + i * kPriorK;
    const std::int64_t last_row = table.q.rows() - 1;
    const bool known = !std::isnan(r[0]);
    // prior.py's follow_library for one probe: where each match's continuation is, and whether its
    // clip reaches that far.
    std::array<std::int64_t, kPriorK> start, below;
    std::array<double, kPriorK> f, w;
    double total = 0.0;
    for (int k = 0; k < kPriorK; ++k) {
      start[k] = std::isnan(r[k]) ? 0 : static_cast<std::int64_t>(r[k]);
      const double later = static_cast<double>(start[k]) + t * table.rate;
      below[k] = static_cast<std::int64_t>(std::floor(later));
      const bool inside = known && below[k] + 1 <= table.last[start[k]];
      if (!inside) below[k] = start[k];
      f[k] = later - static_cast<double>(below[k]);
      w[k] = wk[k] * (inside ? 1.0 : 0.0);
      total += w[k];
    }
    const bool none = total == 0.0;
    for (int k = 0; k < kPriorK; ++k) w[k] = w[k] / (none ? 1.0 : total);
    for (std::size_t j = 0; j < leg.dofs.size(); ++j) {
      const int dof = leg.dofs[j];
      const double sign = leg.signs[j];
      const double lq0 = q0[dof] * sign, lv0 = v0[dof] * sign, la0 = a0[dof] * sign;
      if (none) {
        q[dof] = (lq0 + lv0 * t) * sign;
        v[dof] = lv0 * sign;
        a[dof] = 0.0 * sign;
        continue;
      }
      double v_start = 0.0, a_start = 0.0, dq = 0.0, dv = 0.0, acc = 0.0;
      for (int k = 0; k < kPriorK; ++k) {
        const double mine = known ? wk[k] : 0.0;
        const std::int64_t s = start[k], b = below[k], next = std::min(below[k] + 1, last_row);
        const std::int64_t before = s - 1 < 0 ? last_row : s - 1;  // numpy's index -1
        const double qs = table.q(s, j), vs = table.v(s, j);
        v_start += mine * vs;
        a_start += mine * ((vs - table.v(before, j)) * table.rate);
        dq += w[k] * (((1.0 - f[k]) * table.q(b, j) + f[k] * table.q(next, j)) - qs);
        dv += w[k] * (((1.0 - f[k]) * table.v(b, j) + f[k] * table.v(next, j)) - vs);
        acc += w[k] * ((table.v(next, j) - table.v(b, j)) * table.rate);
      }
      const double dv0 = lv0 - v_start, da0 = la0 - a_start;
      double lq = lq0 + dq;
      lq = lq + dv0 * (kFade * (1.0 - fade)) + da0 * (kFade * kFade * (u - 1.0 + fade));
      const double lv = lv0 + dv - dv0 * (1.0 - fade) + da0 * (kFade * (1.0 - fade));
      const double la = acc - dv0 * (fade / kFade) + da0 * fade;
      q[dof] = lq * sign;
      v[dof] = lv * sign;
      a[dof] = la * sign;
    }
  }
}

}  // namespace jitdyn
