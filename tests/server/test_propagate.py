"""Batched sigma-point propagation (server/estimation/propagate.py) on the shared pool (server/estimation/pool.py):
both back-ends, any worker count, give exactly what a plain mj_step loop over one MjData gives."""

from __future__ import annotations

import threading

import mujoco
import numpy as np
import pytest

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.server.estimation.pool import Backend, WorkerPool
from jitdyn.server.estimation.propagate import Inputs, Propagator, process_model

PENDULUM_2 = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <body>
      <joint name="a" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05" mass="1"/>
      <body pos="0 0 -1">
        <joint name="b" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05" mass="1"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="a" gear="1"/>
    <motor joint="b" gear="1"/>
  </actuator>
</mujoco>
"""

# Slides and a hinge on a floor: contacts, so the constraint solver runs.
HOPPER = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <body pos="0 0 0.3">
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="z" type="slide" axis="0 0 1"/>
      <joint name="hip" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.05" mass="1"/>
      <geom type="sphere" pos="0.1 0 -0.3" size="0.06" mass="0.2"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="hip" gear="1"/>
  </actuator>
</mujoco>
"""

# A muscle on a tendon: activation state (na = 1).
MUSCLE = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <site name="origin" pos="0 0 0.2"/>
    <body>
      <joint name="elbow" type="hinge" axis="0 1 0" range="-2 2" limited="true"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/>
      <site name="insertion" pos="0.2 0 0.02"/>
    </body>
  </worldbody>
  <tendon>
    <spatial name="t"><site site="origin"/><site site="insertion"/></spatial>
  </tendon>
  <actuator>
    <muscle tendon="t" name="m"/>
  </actuator>
</mujoco>
"""

MODELS = {
    "pendulum_2": PENDULUM_2,
    # What MuJoCo leaves in qacc after a step depends on the integrator (RK4: its last stage's).
    "pendulum_2_rk4": PENDULUM_2.replace('timestep="0.01"', 'timestep="0.01" integrator="RK4"'),
    "hopper_implicitfast": HOPPER.replace('timestep="0.002"', 'timestep="0.002" integrator="implicitfast"'),
    "hopper": HOPPER,
    "muscle": MUSCLE,
}
SCENARIO_OF = {Inputs.NONE: "PASSIVE", Inputs.CTRL: "CONTROLLED", Inputs.QFRC: "EXTERNAL"}


def _sigma_set(model: mujoco.MjModel, nsigma: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    qpos = model.qpos0 + 0.3 * rng.standard_normal((nsigma, model.nq))
    qvel = rng.standard_normal((nsigma, model.nv))
    return qpos, qvel


def _reference(
    model: mujoco.MjModel,
    qpos: np.ndarray,
    qvel: np.ndarray,
    act: np.ndarray,
    ctrl: np.ndarray,
    qfrc: np.ndarray,
    nstep: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The plain loop: one fresh MjData per point, mj_step nstep times."""
    out = [
        np.empty((len(qpos), model.nq)),
        np.empty((len(qpos), model.nv)),
        np.empty((len(qpos), model.na)),
        np.empty((len(qpos), model.nv)),
    ]
    for i in range(len(qpos)):
        d = mujoco.MjData(model)
        d.qpos[:], d.qvel[:], d.act[:], d.ctrl[:], d.qfrc_applied[:] = qpos[i], qvel[i], act, ctrl, qfrc
        for _ in range(nstep):
            mujoco.mj_step(model, d)
        out[0][i], out[1][i], out[2][i], out[3][i] = d.qpos, d.qvel, d.act, d.qacc
    return out[0], out[1], out[2], out[3]


@pytest.mark.parametrize("backend", list(Backend))
@pytest.mark.parametrize("workers", [1, 2, 3])
@pytest.mark.parametrize("inputs", list(Inputs))
@pytest.mark.parametrize("name", list(MODELS))
def test_backends_equal_a_plain_mj_step_loop(
    backend: Backend, workers: int, inputs: Inputs, name: str
) -> None:
    model = process_model(mujoco.MjModel.from_xml_string(MODELS[name]), scenario=SCENARIO_OF[inputs])
    nsigma, nstep = 7, 5
    qpos, qvel = _sigma_set(model, nsigma, seed=1)
    act = np.full(model.na, 0.4)
    rng = np.random.default_rng(2)
    ctrl = rng.uniform(0.0, 1.0, model.nu)
    qfrc = rng.standard_normal(model.nv)
    with WorkerPool(workers, backend=backend) as pool:
        propagate = Propagator(
            model, pool=pool, nsigma=nsigma, nstep=nstep, inputs=inputs, want_qacc=True, min_chunk_seconds=0
        )
        out = propagate(qpos, qvel, act=act, ctrl=ctrl, qfrc=qfrc)
        expected = _reference(
            model,
            qpos,
            qvel,
            act,
            ctrl if inputs is Inputs.CTRL else np.zeros(model.nu),
            qfrc if inputs is Inputs.QFRC else np.zeros(model.nv),
            nstep,
        )
    np.testing.assert_array_equal(out.qpos, expected[0])
    np.testing.assert_array_equal(out.qvel, expected[1])
    np.testing.assert_array_equal(out.act, expected[2])
    assert out.qacc is not None
    np.testing.assert_array_equal(out.qacc, expected[3])


@pytest.mark.parametrize("backend", list(Backend))
def test_other_step_counts_and_repeated_calls(backend: Backend) -> None:
    model = process_model(mujoco.MjModel.from_xml_string(PENDULUM_2), scenario="CONTROLLED")
    qpos, qvel = _sigma_set(model, 5, seed=3)
    ctrl = np.array([0.2, -0.1])
    with WorkerPool(2, backend=backend) as pool:
        propagate = Propagator(
            model, pool=pool, nsigma=5, nstep=5, inputs=Inputs.CTRL, want_qacc=True, min_chunk_seconds=0
        )
        for nstep in (5, 1, 12, 5, 3):
            out = propagate(qpos, qvel, act=np.zeros(0), ctrl=ctrl, nstep=nstep)
            expected = _reference(model, qpos, qvel, np.zeros(0), ctrl, np.zeros(2), nstep)
            np.testing.assert_array_equal(out.qpos, expected[0])
            np.testing.assert_array_equal(out.qacc, expected[3])  # type: ignore[arg-type]


def test_qacc_is_not_computed_unless_asked() -> None:
    model = process_model(mujoco.MjModel.from_xml_string(PENDULUM_2), scenario="PASSIVE")
    with WorkerPool(1) as pool:
        out = Propagator(model, pool=pool, nsigma=3, nstep=2, inputs=Inputs.NONE)(
            *_sigma_set(model, 3, seed=4), act=np.zeros(0)
        )
    assert out.qacc is None


def test_sessions_share_one_pool_from_several_threads() -> None:
    model = process_model(mujoco.MjModel.from_xml_string(HOPPER), scenario="CONTROLLED")
    sets = [_sigma_set(model, 9, seed=s) for s in range(4)]
    ctrl = np.array([0.5])
    results: dict[int, list[np.ndarray]] = {}
    with WorkerPool(2) as pool:
        propagators = [
            Propagator(
                model, pool=pool, nsigma=9, nstep=5, inputs=Inputs.CTRL, want_qacc=True, min_chunk_seconds=0
            )
            for _ in sets
        ]

        def session(i: int) -> None:
            results[i] = []
            for _ in range(20):
                out = propagators[i](*sets[i], act=np.zeros(0), ctrl=ctrl)
                results[i].append(out.qpos.copy())

        threads = [threading.Thread(target=session, args=(i,)) for i in range(len(sets))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    for i, (qpos, qvel) in enumerate(sets):
        expected = _reference(model, qpos, qvel, np.zeros(0), ctrl, np.zeros(model.nv), 5)[0]
        for got in results[i]:
            np.testing.assert_array_equal(got, expected)


def test_process_model_is_a_private_copy() -> None:
    model = mujoco.MjModel.from_xml_string(MUSCLE)
    before = int(model.opt.disableflags)
    private = process_model(model, scenario="EXTERNAL")
    assert int(model.opt.disableflags) == before
    for flag in ("mjDSBL_WARMSTART", "mjDSBL_AUTORESET", "mjDSBL_SENSOR", "mjDSBL_ACTUATION"):
        assert private.opt.disableflags & int(getattr(mujoco.mjtDisableBit, flag)), flag
    assert not process_model(model, scenario="CONTROLLED").opt.disableflags & int(
        mujoco.mjtDisableBit.mjDSBL_ACTUATION
    )


def test_external_process_model_drops_only_tendons_that_do_nothing() -> None:
    sprung = MUSCLE.replace('<spatial name="t">', '<spatial name="t" stiffness="50" springlength="0.1">')
    for xml, dropped in ((MUSCLE, True), (sprung, False)):
        model = mujoco.MjModel.from_xml_string(xml)
        private = process_model(model, scenario="EXTERNAL")
        assert (private.tendon_num[0] == 0) == dropped
        assert process_model(model, scenario="CONTROLLED").tendon_num[0] == model.tendon_num[0]
        # Same states as the model with only its actuators off.
        plain = mujoco.MjModel.from_xml_string(xml)
        plain.opt.disableflags = private.opt.disableflags
        qpos, qvel = _sigma_set(model, 5, seed=6)
        with WorkerPool(1) as pool:
            out = Propagator(private, pool=pool, nsigma=5, nstep=20, inputs=Inputs.QFRC)(
                qpos, qvel, act=np.array([0.7]), qfrc=np.array([0.3])
            )
        expected = _reference(plain, qpos, qvel, np.array([0.7]), np.zeros(1), np.array([0.3]), 20)
        np.testing.assert_array_equal(out.qpos, expected[0])
        np.testing.assert_array_equal(out.qvel, expected[1])


@pytest.mark.parametrize("scenario", ["PASSIVE", "CONTROLLED", "DRIVEN"])
def test_contacts_are_off_only_where_no_two_geoms_can_touch(scenario: str) -> None:
    """The muscle arm with a second geom that no other can collide with (conaffinity 0 on both, as
    every geom of myoElbow): its process model skips the collision pass and steps to the same
    states as the model with contacts on; the hopper on its floor keeps its contacts."""
    apart = MUSCLE.replace('size="0.03" mass="0.5"/>', 'size="0.03" mass="0.5" conaffinity="0"/>')
    apart = apart.replace(
        '<site name="origin"',
        '<geom type="sphere" size="0.05" pos="0.3 0 0" conaffinity="0"/><site name="origin"',
    )
    contact = int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    assert (
        process_model(mujoco.MjModel.from_xml_string(HOPPER), scenario=scenario).opt.disableflags & contact
        == 0
    )
    model = mujoco.MjModel.from_xml_string(apart)
    private = process_model(model, scenario=scenario)
    assert private.opt.disableflags & contact
    plain = mujoco.MjModel.from_xml_string(apart)
    plain.opt.disableflags = private.opt.disableflags & ~contact
    plain.tendon_num[:] = private.tendon_num
    qpos, qvel = _sigma_set(model, 5, seed=8)
    qfrc = np.array([0.3])
    ctrl = np.array([0.6])
    with WorkerPool(1) as pool:
        inputs = (
            Inputs.CTRL if scenario == "CONTROLLED" else Inputs.QFRC if scenario == "DRIVEN" else Inputs.NONE
        )
        out = Propagator(private, pool=pool, nsigma=5, nstep=50, inputs=inputs, want_qacc=True)(
            qpos, qvel, act=np.array([0.7]), ctrl=ctrl, qfrc=qfrc
        )
    expected = _reference(
        plain,
        qpos,
        qvel,
        np.array([0.7]),
        ctrl if inputs is Inputs.CTRL else np.zeros(1),
        qfrc if inputs is Inputs.QFRC else np.zeros(1),
        50,
    )
    for got, want in zip((out.qpos, out.qvel, out.act, out.qacc), expected, strict=True):
        np.testing.assert_array_equal(got, want)


def test_a_diverging_point_stays_non_finite_instead_of_resetting() -> None:
    model = process_model(mujoco.MjModel.from_xml_string(PENDULUM_2), scenario="PASSIVE")
    qpos, qvel = _sigma_set(model, 3, seed=5)
    qvel[1] = np.nan
    with WorkerPool(1) as pool:
        out = Propagator(model, pool=pool, nsigma=3, nstep=2, inputs=Inputs.NONE)(qpos, qvel, act=np.zeros(0))
    assert np.all(np.isfinite(out.qpos[[0, 2]]))
    assert not np.all(np.isfinite(out.qvel[1]))


def test_a_pool_leaves_blas_on_its_callers_thread() -> None:
    """numpy's and scipy's OpenBLAS run single-threaded once a process has a pool: their own
    threads, spinning after each call, fought the pool's for the cores (myoHand's cycle)."""
    from threadpoolctl import threadpool_info

    with WorkerPool(2):
        blas = [info for info in threadpool_info() if info["user_api"] == "blas"]
    assert blas, "no BLAS found: the limit would be vacuous"
    assert {(info["prefix"], info["num_threads"]) for info in blas} == {(info["prefix"], 1) for info in blas}


def test_pool_lifecycle() -> None:
    pool = WorkerPool(2, backend="THREADS")
    assert (pool.workers, pool.backend, pool.closed) == (2, Backend.THREADS, False)
    assert repr(pool) == "WorkerPool(workers=2, backend=THREADS, open)"
    pool.close()
    pool.close()
    assert pool.closed
    with pytest.raises(FailedPrecondition, match="^the worker pool is closed$"):
        pool.run_chunks(lambda worker, lo, hi: None, 4, chunks=1)
    with WorkerPool(1) as rollout_pool:
        assert rollout_pool.backend is Backend.ROLLOUT
    assert rollout_pool.closed


@pytest.mark.parametrize(
    ("workers", "backend", "message"),
    [
        (0, "ROLLOUT", r"^workers must be an integer in \[1, 256\], got 0$"),
        (True, "ROLLOUT", r"^workers must be an integer in \[1, 256\], got True$"),
        (2.0, "ROLLOUT", r"^workers must be an integer in \[1, 256\], got 2.0$"),
        (2, "GPU", r"^backend must be one of \['ROLLOUT', 'THREADS'\], got 'GPU'$"),
    ],
)
def test_pool_rejects_bad_settings(workers: object, backend: str, message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        WorkerPool(workers, backend=backend)  # type: ignore[arg-type]


def test_chunks_cover_the_set_once_and_errors_propagate() -> None:
    seen: list[tuple[int, int, int]] = []
    lock = threading.Lock()

    def record(worker: int, lo: int, hi: int) -> None:
        with lock:
            seen.append((worker, lo, hi))

    with WorkerPool(3, backend="THREADS") as pool:
        pool.run_chunks(record, 10, chunks=5)
        assert sorted(seen) == [(0, 0, 3), (1, 3, 6), (2, 6, 10)]
        seen.clear()
        pool.run_chunks(record, 10, chunks=0)  # not worth a hand-off: all on the calling thread
        assert seen == [(0, 0, 10)]

        def fail(worker: int, lo: int, hi: int) -> None:
            if worker == 2:
                raise ValueError("chunk 2 failed")

        with pytest.raises(ValueError, match="chunk 2 failed"):
            pool.run_chunks(fail, 10, chunks=3)
        with pytest.raises(FailedPrecondition, match="^the pool's backend is THREADS, not ROLLOUT$"):
            pool.rollout(
                [],
                [],
                nstep=1,
                control_spec=0,
                initial_state=np.zeros((0, 1)),
                control=None,
                state=np.zeros((0, 1, 1)),
                chunks=1,
            )
