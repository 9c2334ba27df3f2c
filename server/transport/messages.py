"""Conversions at the edge of server/: tick outcomes into `Result` messages and stored rows.

Inside server/ code works on numpy arrays and frozen dataclasses; these small free functions are the
only place that knows both sides.
"""

from __future__ import annotations

from typing import Any, Final

import numpy as np

from jitdyn.server.runtime.frames import FrameIn, Rejection
from jitdyn.server.runtime.session import SessionCounts, TickOutcome
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import SessionSummaryInfo, TickRecord
from jitdyn.v1 import common_pb2, dynamics_pb2
from jitdyn.vocabulary import Output, Scenario, Source, to_proto

__all__ = [
    "covariance_diagonal",
    "record_tick",
    "rejected_message",
    "rejection_record",
    "result_message",
    "summary_info",
]

# The proto values of the words every result carries, looked up once (to_proto is ~1 us a call).
_SOURCES: Final = {source: dynamics_pb2.Source.ValueType(to_proto(source)) for source in Source}
_SCENARIOS: Final = {
    str(scenario): common_pb2.Scenario.ValueType(to_proto(scenario)) for scenario in Scenario
}


def covariance_diagonal(outcome: TickOutcome) -> np.ndarray | None:
    """The diagonal of the outcome's covariance, (nstate,), a read-only view; None without one.
    The tick's message and its stored row both carry it: computed once, handed to both."""
    estimate = outcome.estimate
    if estimate is None or estimate.covariance is None:
        return None
    return estimate.covariance.diagonal()


def result_message(
    outcome: TickOutcome,
    *,
    outputs: frozenset[Output],
    frame_delay: float,
    receive_to_send_us: int,
    durable_seq: int | None,
    diagonal: np.ndarray | None,
) -> dynamics_pb2.Result:
    """The `Result` of one tick; `diagonal` is `covariance_diagonal(outcome)`."""
    estimate = outcome.estimate
    result = dynamics_pb2.Result(
        seq=outcome.seq,
        t=outcome.t,
        source=_SOURCES[outcome.source],
        # Lists, not arrays: protobuf reads a list 2-3x faster than a numpy array (1.3 against
        # 3.4 us a field), and a Result has up to eleven vector fields.
        qpos=outcome.qpos.tolist(),
        qvel=outcome.qvel.tolist(),
        qacc=outcome.qacc.tolist(),
        frame_received=outcome.frame is not None,
        late_ticks=outcome.late_ticks,
        frame_delay=frame_delay,
        compute_us=min(outcome.compute_us, 2**32 - 1),
        receive_to_send_us=min(receive_to_send_us, 2**32 - 1),
        horizon=outcome.horizon,
        late_compute=outcome.late_compute,
    )
    dyn = outcome.dynamics
    if dyn.qfrc_inverse is not None:
        result.qfrc_inverse[:] = dyn.qfrc_inverse.tolist()
    if dyn.qacc_forward is not None:
        result.qacc_forward[:] = dyn.qacc_forward.tolist()
    if dyn.actuator_force is not None:
        result.actuator_force[:] = dyn.actuator_force.tolist()
    if dyn.sensordata is not None:
        result.sensordata[:] = dyn.sensordata.tolist()
    if estimate is not None:
        if estimate.covariance is not None and diagonal is not None:
            result.covariance_diagonal[:] = diagonal.tolist()
            if Output.FILTER_STATE in outputs:
                result.covariance[:] = estimate.covariance.ravel().tolist()
        if Output.FILTER_STATE in outputs:
            result.filter_state[:] = np.asarray(estimate.state).tolist()
        if estimate.nis is not None and outcome.source != Source.PREDICTED:
            result.nis = estimate.nis
        result.reinitialised = estimate.reinitialised
        result.adapted = estimate.adapted
        result.absorbed = estimate.absorbed
        if estimate.scenario:
            result.scenario = _SCENARIOS[estimate.scenario]
        if estimate.forecast_weights is not None and outcome.source == Source.PREDICTED:
            result.forecast_weights[:] = estimate.forecast_weights
            if estimate.forecast_predictors is not None:
                result.forecast_predictors[:] = estimate.forecast_predictors
    if durable_seq is not None:
        result.durable_seq = durable_seq
    return result


def rejected_message(rejection: Rejection) -> dynamics_pb2.Rejected:
    return dynamics_pb2.Rejected(
        seq=rejection.seq,
        reason=dynamics_pb2.RejectReason.ValueType(to_proto(rejection.reason)),
        message=rejection.message,
    )


# What a frame brings to its stored row, as the `frame_*` columns.
_FRAME_FIELDS = ("t", "qpos", "qvel", "qacc", "ctrl", "sensordata")
_NO_FRAME: Final = (None,) * 5


def _frame_columns(frame: FrameIn | None) -> dict[str, Any]:
    """The `frame_*` columns of a stored row: the frame's values, or None where none arrived."""
    return {f"frame_{name}": None if frame is None else getattr(frame, name) for name in _FRAME_FIELDS}


def _forecast_weights(outcome: TickOutcome) -> np.ndarray | None:
    """The weights of the forecast combination that answered a PREDICTED tick, as Result has them."""
    estimate = outcome.estimate
    if estimate is None or estimate.forecast_weights is None or outcome.source != Source.PREDICTED:
        return None
    return np.asarray(estimate.forecast_weights, dtype=np.float64)


def record_tick(
    recorder: SessionRecorder,
    outcome: TickOutcome,
    *,
    server_time: float,
    frame_delay: float | None,
    receive_to_send_us: int,
    diagonal: np.ndarray | None,
) -> None:
    """Write the stored row of one tick's answer, with what arrived, straight into the session's
    columns (no `TickRecord`); `diagonal` is `covariance_diagonal(outcome)`, copied here (a view
    of the filter's covariance, which the next tick changes). The other vectors are the tick's
    own, held by reference until the commit thread copies them into their columns."""
    frame = outcome.frame
    estimate = outcome.estimate
    dyn = outcome.dynamics
    if frame is None:
        frame_t = None
        frame_vectors: tuple[np.ndarray | None, ...] = _NO_FRAME
    else:
        frame_t = frame.t
        frame_vectors = (frame.qpos, frame.qvel, frame.qacc, frame.ctrl, frame.sensordata)
    if estimate is None:
        state = nis = None
        reinitialised = False
    else:
        state = estimate.state
        nis = estimate.nis if outcome.source != Source.PREDICTED else None
        reinitialised = bool(estimate.reinitialised)
    recorder.append_result(
        (
            outcome.seq,
            outcome.source,
            outcome.t,
            server_time,
            frame_t,
            outcome.late_ticks,
            frame_delay,
            nis,
            reinitialised,
            outcome.late_compute,
            outcome.compute_us,
            receive_to_send_us,
            (
                *frame_vectors,
                outcome.qpos,
                outcome.qvel,
                outcome.qacc,
                dyn.qfrc_inverse,
                dyn.qacc_forward,
                dyn.actuator_force,
                dyn.sensordata,
                None if diagonal is None else diagonal.copy(),
                state,
                _forecast_weights(outcome),
            ),
        )
    )


def rejection_record(rejection: Rejection, *, server_time: float, t: float) -> TickRecord:
    """The stored row of a rejected frame or skip: the values of a frame that came too late to be
    used are kept (`frame_*`); those of a frame that failed its checks are not."""
    frame = rejection.frame
    return TickRecord(
        kind="rejected",
        # The column is int64; a hostile seq is kept whole in the message.
        seq=min(rejection.seq, 2**63 - 1),
        source="",
        t=t,
        server_time=server_time,
        frame_received=True,
        **_frame_columns(frame),
        late_ticks=0,
        frame_delay=None,
        qpos=None,
        qvel=None,
        qacc=None,
        qfrc_inverse=None,
        qacc_forward=None,
        actuator_force=None,
        sensordata=None,
        covariance_diagonal=None,
        filter_state=None,
        nis=None,
        reinitialised=False,
        compute_us=0,
        receive_to_send_us=0,
        reject_reason=rejection.reason,
        reject_message=rejection.message,
    )


def summary_info(counts: SessionCounts, *, duration: float) -> SessionSummaryInfo:
    stats: dict[str, object] = {}
    if counts.qfrc_min is not None and counts.qfrc_max is not None:
        stats["qfrc_inverse_min"] = counts.qfrc_min.tolist()
        stats["qfrc_inverse_max"] = counts.qfrc_max.tolist()
    if counts.mujoco_warnings:
        stats["mujoco_warnings"] = counts.mujoco_warnings
    if counts.skipped or counts.late_compute:
        stats["overload"] = {"skipped_ticks": counts.skipped, "late_compute_ticks": counts.late_compute}
    return SessionSummaryInfo(
        ticks=counts.ticks,
        frames=counts.frames + counts.rejected,
        measured=counts.measured,
        predicted=counts.predicted,
        corrected=counts.corrected,
        rejected=counts.rejected,
        late=counts.late,
        mean_compute_us=counts.compute_us_total / counts.results if counts.results else 0.0,
        max_compute_us=float(counts.compute_us_max),
        duration=duration,
        stats=stats,
    )
