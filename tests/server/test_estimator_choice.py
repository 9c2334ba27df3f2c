"""A REALTIME session's estimator chosen from the model's cost, measured once when the model is
registered and stored with it (docs/decisions/0204-the-estimator-chosen-by-stored-cost.md): a real
server over gRPC on loopback, its real index, real MuJoCo.

The tests read the stored costs back from the server and hold the choice to them: what is measured
varies with the machine, the choice made from what is stored does not.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import sqlalchemy as sa

from jitdyn.client import Client, SessionOptions
from jitdyn.errors import ResourceExhausted
from jitdyn.storage.db import default_index_url
from jitdyn.v1 import common_pb2, model_registry_pb2

pytest.importorskip("myo_sim")

# The server's --max-tick-share: a quarter, not the default half. A fast machine fits one 2 ms step of
# myoHand's 47 simplex points in half of a 500 Hz tick (0.996 ms of 1 ms, measured in CI), and then
# no rate is left where the UKF does not fit; a quarter keeps a factor of two on this machine.
_SHARE = 0.25
# myoHand's rates: its timestep is 2 ms and a tick is a whole number of steps.
_RATES = tuple(500.0 / steps for steps in range(1, 11))
_UKF = common_pb2.ESTIMATOR_UKF
_DEAD_RECKONING = common_pb2.ESTIMATOR_CONSTANT_VELOCITY
_EKF = common_pb2.ESTIMATOR_EKF

# A pendulum on a 10 us timestep: a tick of 10 us leaves 5 us, which no estimator fits.
_FAST_PENDULUM = """
<mujoco model="fast_pendulum">
  <option timestep="0.00001"/>
  <worldbody>
    <body name="link" pos="0 0 1">
      <joint name="swing" type="hinge" axis="0 1 0" damping="0.01"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03" mass="1"/>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory, make_config: Any) -> Iterator[tuple[Any, Path]]:
    """A server whose admission looks at its own process only: the other programs on a shared
    test machine must not refuse the REALTIME opens whose `opened` these tests read."""
    from jitdyn.server.runtime.limits import StreamLimits
    from jitdyn.server.transport.background import BackgroundServer

    data = tmp_path_factory.mktemp("data")
    with BackgroundServer(make_config(data, stream_limits=StreamLimits(max_tick_share=_SHARE))) as running:
        running.services.admission.count_machine_cpu = False
        yield running, data


@pytest.fixture(scope="module")
def client(served: tuple[Any, Path]) -> Iterator[Client]:
    with Client(served[0].address, timeout=120) as connected:
        yield connected


@pytest.fixture(scope="module")
def hand(client: Client) -> model_registry_pb2.Model:
    """myoHand registered through the server: its costs measured then."""
    from jitdyn.client.myo import pack_myo_model

    mjcf, assets = pack_myo_model("myohand")
    client.register_model(name="hand", mjcf=mjcf, assets=assets)
    return client.get_model_message(name="hand")


def _candidates(model: model_registry_pb2.Model, scenario: int) -> list[model_registry_pb2.EstimatorCost]:
    return [cost for cost in model.estimator_costs if cost.scenario == scenario]


def _expected(
    model: model_registry_pb2.Model, scenario: int, rate: float
) -> model_registry_pb2.EstimatorCost:
    """The rule, read from the stored figures: the first candidate whose max_rate reaches `rate`."""
    return next(cost for cost in _candidates(model, scenario) if cost.max_rate >= rate - 1e-9)


def test_registration_stores_each_candidates_cost(client: Client, hand: model_registry_pb2.Model) -> None:
    scenarios = {cost.scenario for cost in hand.estimator_costs}
    assert scenarios == {
        common_pb2.SCENARIO_PASSIVE,
        common_pb2.SCENARIO_CONTROLLED,
        common_pb2.SCENARIO_EXTERNAL,
        common_pb2.SCENARIO_DRIVEN,
    }
    external = _candidates(hand, common_pb2.SCENARIO_EXTERNAL)
    # myoHand's state of 46 takes simplex points already; then dead reckoning, which always fits;
    # the linearised filter is timed and shown after it (chosen by name only, decision 0210).
    assert [(c.estimator, c.sigma_points) for c in external] == [
        (_UKF, common_pb2.SIGMA_POINTS_SIMPLEX),
        (_DEAD_RECKONING, common_pb2.SIGMA_POINTS_UNSPECIFIED),
        (_EKF, common_pb2.SIGMA_POINTS_UNSPECIFIED),
    ]
    passive = _candidates(hand, common_pb2.SCENARIO_PASSIVE)
    assert _EKF not in [c.estimator for c in passive]  # EXTERNAL and DRIVEN only
    assert _EKF in [c.estimator for c in _candidates(hand, common_pb2.SCENARIO_DRIVEN)]
    for cost in hand.estimator_costs:
        assert list(cost.steps) == [1, 2, 5, 10]
        assert all(seconds > 0 for seconds in cost.seconds), cost
    ukf, reckoning, ekf = external
    assert ukf.seconds[-1] > 20 * reckoning.seconds[-1]  # 47 points of 10 steps against none
    # Ten steps a tick are two linearisations of 10 ms steps: far less than 47 points of ten.
    assert ukf.seconds[-1] > 3 * ekf.seconds[-1] > 3 * reckoning.seconds[-1]
    # Stored, not measured again: the same figures on every read.
    again = client.get_model_message(name="hand")
    assert list(again.estimator_costs) == list(hand.estimator_costs)
    assert list(again.estimator_choices) == list(hand.estimator_choices)


def _rate_over(cost: model_registry_pb2.EstimatorCost, *, within: float = float("inf")) -> float:
    """The highest of myoHand's rates, at most `within`, that `cost` does not fit: the tests take
    their rates from the stored costs, so that a faster or slower machine moves the rate, not the
    rule. Fails, naming the cost, where no rate is left."""
    rate = next((r for r in _RATES if cost.max_rate < r - 1e-9 and r <= within + 1e-9), None)
    assert rate is not None, f"this machine fits {cost} at every rate of {_RATES}"
    return rate


def test_a_rate_the_ukf_cannot_fit_gets_the_cheaper_estimator_and_says_so(
    client: Client, hand: model_registry_pb2.Model
) -> None:
    ukf = _candidates(hand, common_pb2.SCENARIO_EXTERNAL)[0]
    # One 2 ms step of 47 points' physics: over a quarter of a 500 Hz tick on the machines seen.
    rate = _rate_over(ukf)
    steps = round(500.0 / rate)
    expected = _expected(hand, common_pb2.SCENARIO_EXTERNAL, rate)
    assert expected.estimator == _DEAD_RECKONING
    name = common_pb2.Estimator.Name(expected.estimator)
    dt = 0.002 * steps
    options = SessionOptions(model_name="hand", scenario="EXTERNAL", dt=dt, clock="REALTIME")
    reasons = []
    for _ in range(2):  # the choice comes from the stored cost: the same at every open
        with client.open_session(options) as session:
            opened = session.opened
            assert opened.estimator["estimator"] == name.removeprefix("ESTIMATOR_")
            assert opened.estimator_choice == "BY_COST"
            reasons.append(opened.estimator_reason)
    assert reasons[0] == reasons[1]
    assert re.match(
        rf"chosen by cost, measured once when the model was registered: {name} costs "
        rf"[\d.]+ ms a tick, within {_SHARE:g} of dt {dt * 1e3:g} ms \(--max-tick-share\); ESTIMATOR_UKF "
        r"with SIGMA_POINTS_SIMPLEX costs [\d.]+ ms, over it",
        reasons[0],
    ), reasons[0]
    if steps in ukf.steps:  # a timed step count is quoted as measured
        assert f"SIMPLEX costs {ukf.seconds[list(ukf.steps).index(steps)] * 1e3:.3g} ms" in reasons[0]


def test_the_linearised_filter_is_shown_but_dead_reckoning_is_chosen_where_both_fit(
    client: Client, hand: model_registry_pb2.Model
) -> None:
    """myoHand EXTERNAL at a rate where the UKF's 47 simplex points are over the share of a tick
    and one linearisation is not: dead reckoning comes first (decision 0210: its gaps were the more
    accurate). Asked for by name, the EKF runs at that rate and answers."""
    candidates = _candidates(hand, common_pb2.SCENARIO_EXTERNAL)
    ukf = candidates[0]
    ekf = next(c for c in candidates if c.estimator == _EKF)
    rate = _rate_over(ukf, within=ekf.max_rate)
    assert ekf.max_rate >= rate - 1e-9, f"the EKF fits no rate the UKF does not: {ukf} {ekf}"
    assert _expected(hand, common_pb2.SCENARIO_EXTERNAL, rate).estimator == _DEAD_RECKONING
    dt = 1.0 / rate
    options = SessionOptions(model_name="hand", scenario="EXTERNAL", dt=dt, clock="REALTIME")
    with client.open_session(options) as session:
        assert session.opened.estimator["estimator"] == "CONSTANT_VELOCITY"
        assert session.opened.estimator_choice == "BY_COST"
    asked = SessionOptions(
        model_name="hand", scenario="EXTERNAL", dt=dt, clock="REALTIME", estimator={"estimator": "EKF"}
    )
    with client.open_session(asked) as session:
        assert session.opened.estimator["estimator"] == "EKF"
        assert session.opened.estimator["noise_model"] == "FIXED"
        assert session.opened.estimator_choice == "ASKED"


def test_the_linearised_filter_asked_by_name_runs_a_session(client: Client) -> None:
    """pendulum_2 in DRIVEN with estimator EKF: asked for, it runs whatever the cost, and answers
    a skipped tick from its own prediction."""
    import numpy as np

    from jitdyn.client import FrameData, TickResult

    options = SessionOptions(
        model_name="pendulum_2", scenario="DRIVEN", dt=0.05, estimator={"estimator": "EKF"}
    )
    with client.open_session(options) as session:
        assert session.opened.estimator["estimator"] == "EKF"
        assert session.opened.estimator_choice == "ASKED"
        answers = []
        for k in range(20):
            q = [0.3 * np.cos(k * 0.05), 0.0]
            v = [-0.3 * np.sin(k * 0.05), 0.0]
            answer = (
                session.skip(k)
                if k % 5 == 4
                else session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=v))
            )
            assert isinstance(answer, TickResult), answer
            answers.append(answer)
    assert all(np.all(np.isfinite(a.qpos)) for a in answers)
    assert answers[9].source != answers[8].source  # a skipped tick is predicted, not measured


def test_the_linearised_filter_refuses_what_it_does_not_run(client: Client) -> None:
    from jitdyn.errors import InvalidArgument

    options = SessionOptions(
        model_name="pendulum_2", scenario="CONTROLLED", dt=0.05, estimator={"estimator": "EKF"}
    )
    with pytest.raises(InvalidArgument, match="scenario must be PASSIVE, EXTERNAL or DRIVEN, got CONTROLLED"):
        client.open_session(options)


def test_an_explicit_choice_or_lockstep_overrides_the_cost(
    client: Client, hand: model_registry_pb2.Model
) -> None:
    asked = SessionOptions(
        model_name="hand", scenario="EXTERNAL", dt=0.002, estimator={"estimator": "STATIC"}, clock="REALTIME"
    )
    with client.open_session(asked) as session:
        assert session.opened.estimator["estimator"] == "STATIC"
        assert session.opened.estimator_choice == "ASKED"
        assert session.opened.estimator_reason == "asked for: open.estimator sets estimator"
    lockstep = SessionOptions(model_name="hand", scenario="EXTERNAL", dt=0.002)
    with client.open_session(lockstep) as session:
        assert session.opened.estimator["estimator"] == "UKF"
        assert session.opened.estimator["sigma_points"] == "SIMPLEX"
        assert session.opened.estimator_choice == "PRESET"
        assert session.opened.estimator_reason == "the preset's: CLOCK_LOCKSTEP has no tick to fit"


def test_a_small_model_keeps_its_full_ukf(client: Client) -> None:
    shown = client.get_model_message(name="pendulum_3")
    expected = _expected(shown, common_pb2.SCENARIO_PASSIVE, 20.0)
    assert (expected.estimator, expected.sigma_points) == (_UKF, common_pb2.SIGMA_POINTS_MERWE)
    options = SessionOptions(model_name="pendulum_3", scenario="PASSIVE", dt=0.05, clock="REALTIME")
    with client.open_session(options) as session:
        assert session.opened.estimator["sigma_points"] == "MERWE"
        assert session.opened.estimator_choice == "BY_COST"
        assert "ESTIMATOR_UKF with SIGMA_POINTS_MERWE, the most accurate candidate" in (
            session.opened.estimator_reason
        )
    simplex = SessionOptions(
        model_name="pendulum_3",
        scenario="PASSIVE",
        dt=0.05,
        clock="REALTIME",
        estimator={"sigma_points": "SIMPLEX"},
    )
    with client.open_session(simplex) as session:
        assert session.opened.estimator["sigma_points"] == "SIMPLEX"
        assert session.opened.estimator_choice == "ASKED"


def test_a_rate_nothing_fits_is_refused_with_the_rate_that_would(client: Client) -> None:
    client.register_model(name="fast_pendulum", mjcf=_FAST_PENDULUM, assets={})
    shown = client.get_model_message(name="fast_pendulum")
    passive = _candidates(shown, common_pb2.SCENARIO_PASSIVE)
    fastest = max(passive, key=lambda cost: cost.max_rate)
    assert fastest.estimator == _DEAD_RECKONING and 0 < fastest.max_rate < 100_000
    options = SessionOptions(model_name="fast_pendulum", scenario="PASSIVE", dt=0.00001, clock="REALTIME")
    with pytest.raises(ResourceExhausted) as refused:
        client.open_session(options)
    message = str(refused.value)
    assert "no estimator of this model fits a tick of 100000 Hz in SCENARIO_PASSIVE" in message, message
    named = re.search(
        r"at most ([\d.e+]+) Hz \(open\.dt ([\d.e-]+) s\) fits ESTIMATOR_CONSTANT_VELOCITY", message
    )
    assert named is not None, message
    assert float(named.group(1)) == pytest.approx(fastest.max_rate, rel=1e-5)


def test_models_show_prints_the_costs_and_the_choice_at_a_few_rates(
    served: tuple[Any, Path], hand: model_registry_pb2.Model
) -> None:
    environ = {k: v for k, v in os.environ.items() if not k.startswith("JITDYN_")}
    code = "import sys\nfrom jitdyn.cli import main\nsys.exit(main(sys.argv[1:]))"
    result = subprocess.run(
        [sys.executable, "-c", code, "models", "show", "hand", "--server", served[0].address],
        capture_output=True,
        text=True,
        env=environ,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    shown = json.loads(result.stdout)
    costs = shown["estimator_costs"]
    # 4 scenarios x (UKF, dead reckoning), and the linearised filter in EXTERNAL and DRIVEN
    assert len(costs) == len(hand.estimator_costs) == 10
    assert [c["estimator"] for c in costs if c["scenario"] == "SCENARIO_EXTERNAL"] == [
        "ESTIMATOR_UKF",
        "ESTIMATOR_CONSTANT_VELOCITY",
        "ESTIMATOR_EKF",
    ]
    assert costs[0]["scenario"] == "SCENARIO_PASSIVE" and costs[0]["steps"] == [1, 2, 5, 10]
    choices = [c for c in shown["estimator_choices"] if c["scenario"] == "SCENARIO_EXTERNAL"]
    assert [c["rate"] for c in choices] == [500.0, 250.0, 100.0, 50.0, 20.0]
    for choice in choices:
        expected = _expected(hand, common_pb2.SCENARIO_EXTERNAL, choice["rate"])
        assert choice["estimator"] == common_pb2.Estimator.Name(expected.estimator)


def test_a_model_without_stored_costs_is_measured_at_first_use(
    client: Client, served: tuple[Any, Path]
) -> None:
    """The built-in models, like any registered before costs were stored, have none until first
    used; a listing says so (none), the first show or open measures and stores them."""
    engine = sa.create_engine(default_index_url(served[1]))
    try:
        with engine.begin() as connection:  # as a model registered before the migration
            connection.execute(sa.text("DELETE FROM model_costs"))
        listed = {m.name: m for m in client.list_models(name="pendulum_2")}
        assert listed  # the listing did not fail
        raw = client.get_model_message(name="pendulum_2")
        assert raw.estimator_costs and raw.estimator_choices
        with engine.connect() as connection:
            stored = connection.execute(sa.text("SELECT count(*) FROM model_costs")).scalar_one()
        assert stored == 1
        options = SessionOptions(model_name="biped", scenario="PASSIVE", dt=0.002, clock="REALTIME")
        with client.open_session(options) as session:  # measured at the open, then chosen from
            assert session.opened.estimator_choice == "BY_COST"
        with engine.connect() as connection:
            stored = connection.execute(sa.text("SELECT count(*) FROM model_costs")).scalar_one()
        assert stored == 2
    finally:
        engine.dispose()


@pytest.mark.parametrize(
    ("seconds", "rate"),
    [
        ((0.0009, 0.0010, 0.0013, 0.0018), 500.0),  # 1.0 ms in a 2 ms tick's 1 ms
        ((0.004, 0.004, 0.004, 0.004), 125.0),  # a flat 4 ms fits from 8 steps, between the timed 5 and 10
        ((0.003, 0.004, 0.007, 0.012), 0.0),  # 1 ms more a 1 ms step: over half of any tick
        ((0.0001, 0.0002, 0.0005, 0.001), 1000.0),
    ],
)
def test_the_highest_rate_a_cost_fits(seconds: tuple[float, ...], rate: float) -> None:
    from jitdyn.registry import CandidateCost
    from jitdyn.server.runtime.choice import CostTable

    cost = CandidateCost(
        scenario="PASSIVE", estimator="UKF", sigma_points="MERWE", steps=(1, 2, 5, 10), seconds=seconds
    )
    table = CostTable(costs=(cost,), timestep=0.001, share=0.5)
    assert table.max_rate(cost) == pytest.approx(rate)
    if rate:
        assert table.fits(cost, 1 / rate) and (rate == 1000.0 or not table.fits(cost, 1 / rate - 0.001))


def test_a_server_set_to_the_presets_choice_keeps_it(
    tmp_path: Path, make_config: Any, hand: model_registry_pb2.Model
) -> None:
    """`jitdyn serve --estimator-choice preset`: a REALTIME session that names no estimator gets
    the preset's, whatever the stored cost says; the costs are still measured and shown."""
    from jitdyn.server.transport.app import ServerConfig
    from jitdyn.server.transport.background import BackgroundServer
    from jitdyn.settings import resolve

    settings = resolve({}, {"JITDYN_ESTIMATOR_CHOICE": "PRESET"})
    assert settings.estimator_choice == "preset"
    assert ServerConfig.from_settings(resolve({}, {})).choose_by_cost
    chosen = ServerConfig.from_settings(settings).choose_by_cost
    with BackgroundServer(make_config(tmp_path, choose_by_cost=chosen)) as running:
        running.services.admission.count_machine_cpu = False
        with Client(running.address, timeout=120) as client:
            options = SessionOptions(model_name="pendulum_3", scenario="PASSIVE", dt=0.05, clock="REALTIME")
            with client.open_session(options) as session:
                assert session.opened.estimator["sigma_points"] == "MERWE"
                assert session.opened.estimator_choice == "PRESET"
                assert session.opened.estimator_reason == (
                    "the preset's: this server runs --estimator-choice preset"
                )
            assert client.get_model_message(name="pendulum_3").estimator_costs


def test_a_model_with_nothing_to_estimate_registers_with_no_candidates(client: Client) -> None:
    """No dof, no estimator: the registration goes on, with no costs to show."""
    still = '<mujoco model="still"><worldbody><geom type="box" size="0.1 0.1 0.1"/></worldbody></mujoco>'
    _, created = client.register_model(name="still", mjcf=still, assets={})
    assert created
    shown = client.get_model_message(name="still")
    assert shown.dimensions.nv == 0
    assert not shown.estimator_costs and not shown.estimator_choices
