// The Python face of ukf.h: jitdyn.server.estimation.native._ukf. Only binds; the work is ukf.cc.
// Every call that computes releases the GIL, so the event loop reads frames while a tick runs.
#include <pybind11/eigen.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstdint>
#include <string>

#include "adaptive.h"
#include "forecast.h"
#include "linearised.h"
#include "prior.h"
#include "tick.h"
#include "ukf.h"

namespace py = pybind11;
using jitdyn::Matrix;
using jitdyn::Ukf;
using jitdyn::UkfSpec;
using jitdyn::Vector;

namespace {

std::unique_ptr<Ukf> MakeUkf(std::uintptr_t model_address, int n, int size, int fblocks, bool controlled,
                             int scheme, double scale, const Matrix& unit, const Vector& wm,
                             const Vector& wc, const std::vector<int>& z_index, int nstep, int inputs) {
  if (scheme < 0 || scheme > 2) throw std::invalid_argument("scheme must be 0, 1 or 2, got " + std::to_string(scheme));
  if (inputs < 0 || inputs > 2) throw std::invalid_argument("inputs must be 0, 1 or 2, got " + std::to_string(inputs));
  UkfSpec spec;
  spec.n = n;
  spec.size = size;
  spec.fblocks = fblocks;
  spec.controlled = controlled;
  spec.scheme = static_cast<jitdyn::Scheme>(scheme);
  spec.scale = scale;
  spec.unit = unit;
  spec.wm = wm;
  spec.wc = wc;
  spec.z_index = z_index;
  spec.nstep = nstep;
  spec.inputs = static_cast<jitdyn::Inputs>(inputs);
  return std::make_unique<Ukf>(reinterpret_cast<const mjModel*>(model_address), std::move(spec));
}

template <typename T>
void Assign(T& target, const T& value, const char* name) {
  if (value.rows() != target.rows() || value.cols() != target.cols()) {
    throw std::invalid_argument(std::string(name) + " must have shape (" + std::to_string(target.rows()) +
                                (T::ColsAtCompileTime == 1 ? ",)" : ", " + std::to_string(target.cols()) + ")") +
                                ", got " + std::to_string(value.rows()) + " x " + std::to_string(value.cols()));
  }
  target = value;
}

}  // namespace

PYBIND11_MODULE(_ukf, module) {
  using jitdyn::Adapter;
  using jitdyn::AdapterBounds;
  using jitdyn::AdapterMatrix;
  using jitdyn::AdapterState;
  module.doc() = "jitdyn's unscented Kalman filter on MuJoCo's C API (server/estimation/native/ukf.h)";
  module.attr("MUJOCO_HEADER_VERSION") = mjVERSION_HEADER;
  module.def("mujoco_version", [] { return mj_version(); }, "The version of the libmujoco loaded.");
  py::register_exception<jitdyn::SingularMatrix>(module, "SingularMatrix");

  // A snapshot of an Adapter: opaque and immutable from Python.
  py::class_<AdapterState>(module, "AdapterState");
  py::class_<Adapter>(module, "Adapter")
      .def(py::init([](const Eigen::VectorXd& r0, const AdapterMatrix& q0, const std::vector<bool>& adapt_q,
                       bool inflate, const py::dict& bounds, double nis_limit) {
             auto get = [&](const char* name) { return bounds[name].cast<double>(); };
             auto count = [&](const char* name) { return bounds[name].cast<int>(); };
             AdapterBounds b{get("r_min"),         get("r_max"),         get("q_scale_min"),
                             get("q_scale_max"),   get("forgetting"),    count("window"),
                             get("report_change"), count("window_r"),    count("min_differences"),
                             get("inflation_min"), get("inflation_max"), get("inflation_gain"),
                             get("inflation_leak"), get("inflation_step"), get("gap_gain"),
                             get("gap_step"),      get("absorb_factor")};
             return std::make_unique<Adapter>(r0, q0, adapt_q, inflate, b, nis_limit);
           }),
           py::kw_only(), py::arg("r0"), py::arg("q0"), py::arg("adapt_q"), py::arg("inflate"), py::arg("bounds"),
           py::arg("nis_limit"))
      .def("reset", &Adapter::Reset)
      .def("observe", &Adapter::Observe, py::kw_only(), py::arg("innovation"), py::arg("consecutive"),
           py::arg("gain"), py::arg("nis"), py::arg("noise_share"))
      .def("observe_gap", &Adapter::ObserveGap, py::kw_only(), py::arg("nis"), py::arg("m"))
      .def("absorbed", &Adapter::Absorbed)
      .def("q_for", &Adapter::QFor, py::arg("q0"))
      .def_property_readonly("window_full", &Adapter::window_full)
      .def_property_readonly("r_diagonal", [](const Adapter& a) { return Eigen::VectorXd(a.r()); })
      .def_property_readonly("scale", &Adapter::Scale)
      .def_property_readonly("inflation", &Adapter::Inflation)
      .def_property_readonly("gap_inflation", &Adapter::GapInflation)
      .def("snapshot", [](const Adapter& a) { return a.state(); })
      .def("restore", &Adapter::Restore, py::arg("state"));

  // The forecast combination (forecast.h) and a snapshot of it, opaque and immutable from Python.
  using jitdyn::Combiner;
  using jitdyn::CombinerState;
  py::class_<CombinerState>(module, "CombinerState")
      .def_property_readonly("nbytes", [](const CombinerState& s) { return s.Bytes(); });
  // One choice of the prior's library joints (prior.h), built once and shared by sessions.
  using jitdyn::PriorTable;
  py::class_<PriorTable, std::shared_ptr<PriorTable>>(module, "PriorTable")
      .def(py::init([](double rate, const Matrix& q, const Matrix& v, const std::vector<std::int64_t>& last,
                       const std::vector<std::int64_t>& rows, const Matrix& features, const Vector& spread) {
             auto t = std::make_shared<PriorTable>();
             t->rate = rate;
             t->q = q;
             t->v = v;
             t->last = last;
             t->rows = rows;
             t->features = features;
             t->spread = spread;
             return t;
           }),
           py::kw_only(), py::arg("rate"), py::arg("q"), py::arg("v"), py::arg("last"), py::arg("rows"),
           py::arg("features"), py::arg("spread"))
      .def_property_readonly("candidates", [](const PriorTable& t) { return t.rows.size(); });
  // A leg of the prior: its table, the session's dofs of its joints and their signs.
  using PriorLegs = std::vector<std::tuple<std::shared_ptr<PriorTable>, std::vector<int>, std::vector<double>>>;
  py::class_<Combiner>(module, "Combiner")
      .def(py::init([](std::uintptr_t model_address, double dt, int steps_per_tick, int horizon, const PriorLegs& legs,
                       const std::vector<Eigen::Matrix4d>& prior_cov, const std::vector<Eigen::Matrix4d>& prior_cov_v) {
             const mjModel* m = reinterpret_cast<const mjModel*>(model_address);
             std::unique_ptr<jitdyn::PriorMatcher> prior;
             if (!legs.empty()) {
               std::vector<jitdyn::PriorLeg> made;
               for (const auto& [table, dofs, signs] : legs) made.push_back({table, dofs, signs});
               prior = std::make_unique<jitdyn::PriorMatcher>(std::move(made), m->nv, dt);
             }
             return std::make_unique<Combiner>(m, dt, steps_per_tick, horizon, std::move(prior), prior_cov,
                                               prior_cov_v);
           }),
           py::arg("model_address"), py::kw_only(), py::arg("dt"), py::arg("steps_per_tick"), py::arg("horizon"),
           py::arg("legs") = PriorLegs(),
           py::arg("prior_cov") = std::vector<Eigen::Matrix4d>(), py::arg("prior_cov_v") = std::vector<Eigen::Matrix4d>())
      .def("reset", &Combiner::Reset)
      .def("advance", &Combiner::Advance, py::call_guard<py::gil_scoped_release>())
      .def("observe", &Combiner::Observe, py::arg("qpos"), py::arg("qvel"), py::kw_only(), py::arg("mean_qpos"),
           py::arg("mean_qvel"), py::arg("act"), py::arg("force"), py::arg("rate"),
           py::call_guard<py::gil_scoped_release>())
      .def(
          "forecast",
          [](Combiner& c, const std::optional<Vector>& noise_q, const std::optional<Vector>& noise_qd, bool ended)
              -> std::optional<std::tuple<Vector, Vector, Vector, Vector, Vector, Vector>> {
            std::optional<jitdyn::CombinedForecast> answer;
            {
              py::gil_scoped_release release;
              answer = c.Forecast(noise_q, noise_qd, ended);
            }
            if (!answer) return std::nullopt;
            return std::make_tuple(Vector(answer->weights.head(c.predictors())), answer->qpos, answer->qvel, answer->qacc, answer->var_q,
                                   answer->var_qd);
          },
          py::kw_only(), py::arg("noise_q"), py::arg("noise_qd"), py::arg("ended"))
      .def("fill_window", &Combiner::FillWindow, py::arg("q"), py::arg("v"), py::call_guard<py::gil_scoped_release>())
      .def("snapshot", &Combiner::Snapshot, py::call_guard<py::gil_scoped_release>())
      .def("restore", &Combiner::Restore, py::arg("state"), py::call_guard<py::gil_scoped_release>())
      .def_property_readonly("horizon", &Combiner::horizon)
      .def_property_readonly("nv", &Combiner::nv)
      .def_property_readonly("na", &Combiner::na)
      .def_property_readonly("window", &Combiner::window)
      .def_property_readonly("predictors", &Combiner::predictors)
      .def_property_readonly("tick", &Combiner::tick);

  py::class_<Ukf>(module, "Ukf")
      .def(py::init(&MakeUkf), py::arg("model_address"), py::kw_only(), py::arg("n"), py::arg("size"),
           py::arg("fblocks"), py::arg("controlled"), py::arg("scheme"), py::arg("scale"), py::arg("unit"),
           py::arg("wm"), py::arg("wc"), py::arg("z_index"), py::arg("nstep"), py::arg("inputs"))
      .def("predict", &Ukf::Predict, py::call_guard<py::gil_scoped_release>())
      .def("update", &Ukf::Update, py::arg("z"), py::call_guard<py::gil_scoped_release>())
      .def("sigma_points", &Ukf::SigmaPoints, py::arg("x"), py::arg("P"), py::call_guard<py::gil_scoped_release>())
      .def("propagate", &Ukf::Propagate, py::arg("sigmas"), py::arg("nstep"),
           py::call_guard<py::gil_scoped_release>())
      .def("tidy", &Ukf::Tidy, py::call_guard<py::gil_scoped_release>())
      .def("largest_variance", &Ukf::LargestVariance)
      .def("forward", &Ukf::Forward, py::arg("qpos"), py::arg("qvel"), py::arg("act"), py::arg("ctrl"),
           py::arg("qfrc"), py::call_guard<py::gil_scoped_release>())
      .def_property_readonly("nis", [](const Ukf& u) { return u.nis; })
      .def_property("sigmas_f", &Ukf::sigmas_f, &Ukf::set_sigmas_f)
      .def_property_readonly("nsigma", &Ukf::nsigma)
      .def_property_readonly("nstep", [](const Ukf& u) { return u.spec().nstep; })
      .def_property("repairs", &Ukf::repairs, &Ukf::set_repairs)
      .def_property(
          "x", [](const Ukf& u) { return u.x; }, [](Ukf& u, const Vector& v) { Assign(u.x, v, "x"); })
      .def_property(
          "P", [](const Ukf& u) { return u.P; }, [](Ukf& u, const Matrix& v) { Assign(u.P, v, "P"); })
      .def_property(
          "Q", [](const Ukf& u) { return u.Q; }, [](Ukf& u, const Matrix& v) { Assign(u.Q, v, "Q"); })
      .def_property(
          "R", [](const Ukf& u) { return u.R; }, [](Ukf& u, const Matrix& v) { Assign(u.R, v, "R"); })
      .def_property(
          "act", [](const Ukf& u) { return u.act; }, [](Ukf& u, const Vector& v) { Assign(u.act, v, "act"); })
      .def_property(
          "ctrl", [](const Ukf& u) { return u.ctrl; }, [](Ukf& u, const Vector& v) { Assign(u.ctrl, v, "ctrl"); })
      .def_property(
          "qfrc", [](const Ukf& u) { return u.qfrc; }, [](Ukf& u, const Vector& v) { Assign(u.qfrc, v, "qfrc"); })
      .def_property_readonly("y", [](const Ukf& u) { return u.y; })
      .def_property_readonly("K", [](const Ukf& u) { return u.K; })
      .def_property_readonly("S", [](const Ukf& u) { return u.S; })
      .def_property_readonly("SI", [](const Ukf& u) { return u.SI; })
      .def_property_readonly("propagated_act", [](const Ukf& u) { return u.propagated_act; });

  // The linearised filter (linearised.h): server/estimation/native/linearised.py wraps it.
  py::class_<jitdyn::Ekf>(module, "Ekf")
      .def(py::init([](std::uintptr_t model_address, std::uintptr_t linearised_address, bool driven, int nstep, const jitdyn::Ekf::Matrix& Q,
                       const jitdyn::Ekf::Matrix& R, double eps, double force_eps) {
             return std::make_unique<jitdyn::Ekf>(reinterpret_cast<const mjModel*>(model_address),
                                                  reinterpret_cast<const mjModel*>(linearised_address), driven, nstep,
                                                  Q, R, eps, force_eps);
           }),
           py::arg("model_address"), py::arg("linearised_address"), py::kw_only(), py::arg("driven"), py::arg("nstep"), py::arg("Q"),
           py::arg("R"), py::arg("eps"), py::arg("force_eps"))
      .def("predict", &jitdyn::Ekf::Predict, py::arg("x"), py::arg("P"), py::arg("act"), py::arg("qfrc"),
           py::call_guard<py::gil_scoped_release>())
      .def("update", &jitdyn::Ekf::Update, py::arg("x"), py::arg("P"), py::arg("z"),
           py::call_guard<py::gil_scoped_release>())
      .def_property_readonly("n", &jitdyn::Ekf::n);
  // One tick in one call (tick.h): its own block, apart from the other engines' bindings.
  {
    using jitdyn::Tick;
    using jitdyn::TickSpec;
    using jitdyn::TickState;
    py::class_<TickState>(module, "TickState")
        .def_property_readonly("nbytes", [](const TickState& s) { return s.Bytes(); });
    py::class_<Tick>(module, "Tick")
        .def(py::init([](Ukf* ukf, jitdyn::Adapter* adapter, jitdyn::Combiner* combiner, const Vector& act_low,
                         const Vector& act_high, double covariance_limit, int force) {
               if (force < 0 || force > 2) throw std::invalid_argument("force must be 0, 1 or 2, got " + std::to_string(force));
               TickSpec spec{act_low, act_high, covariance_limit, static_cast<jitdyn::TickForce>(force)};
               return std::make_unique<Tick>(ukf, adapter, combiner, std::move(spec));
             }),
             py::arg("ukf"), py::kw_only(), py::arg("adapter"), py::arg("combiner"), py::arg("act_low"),
             py::arg("act_high"), py::arg("covariance_limit"), py::arg("force"), py::keep_alive<1, 2>(),
             py::keep_alive<1, 3>(), py::keep_alive<1, 4>())
        // (finite, largest_variance, diverged, act)
        .def(
            "advance",
            [](Tick& t, bool gap) {
              jitdyn::TickPrediction p;
              {
                py::gil_scoped_release release;
                p = t.Advance(gap);
              }
              return py::make_tuple(p.finite, p.largest_variance, p.diverged, t.act());
            },
            py::arg("gap"))
        // (updated, finite, nis, largest_variance, observed, adapted, absorb, act, x, P, qacc or None,
        //  observed_frame)
        .def(
            "step",
            [](Tick& t, const Vector& z, bool quiet, const std::optional<Vector>& qvel) {
              jitdyn::TickUpdate u;
              {
                py::gil_scoped_release release;
                u = t.Step(z, quiet, qvel);
              }
              py::object qacc = u.has_qacc ? py::cast(u.qacc) : py::none();
              return py::make_tuple(u.updated, u.finite, u.nis, u.largest_variance, u.observed, u.adapted, u.absorb,
                                    t.act(), t.x(), t.P(), qacc, u.observed_frame);
            },
            py::arg("z"), py::kw_only(), py::arg("quiet"), py::arg("qvel"))
        .def("snapshot", &Tick::Snapshot, py::call_guard<py::gil_scoped_release>())
        .def("restore", &Tick::Restore, py::arg("state"), py::call_guard<py::gil_scoped_release>());
  }
}
