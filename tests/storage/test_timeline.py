"""session_timeline: a session's rows tick by tick, checked value by value on a few inline records
(a tick measured, one predicted then corrected, one predicted only, a late frame rejected)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from jitdyn.storage.columns import records_to_batch
from jitdyn.storage.records import TickRecord
from jitdyn.storage.timeline import session_timeline


def vec(*values: float) -> np.ndarray:
    return np.array(values, dtype=np.float64)


RECORDS = [
    TickRecord(
        kind="result",
        seq=0,
        source="MEASURED",
        t=0.0,
        frame_received=True,
        frame_qpos=vec(0.1, 0.2),
        frame_delay=0.004,
        qpos=vec(0.1, 0.2),
        qfrc_inverse=vec(1.0, 2.0),
        nis=1.5,
        compute_us=40,
        receive_to_send_us=55,
    ),
    TickRecord(
        kind="result",
        seq=1,
        source="PREDICTED",
        t=0.01,
        qpos=vec(0.11, 0.21),
        qfrc_inverse=vec(0.0, 0.0),
        compute_us=90,
        receive_to_send_us=95,
    ),
    TickRecord(kind="result", seq=2, source="PREDICTED", t=0.02, qpos=vec(0.12, 0.22), compute_us=80),
    TickRecord(
        kind="result",
        seq=1,
        source="CORRECTED",
        t=0.01,
        frame_received=True,
        frame_qpos=vec(0.115, 0.215),
        late_ticks=2,
        frame_delay=0.017,
        qpos=vec(0.115, 0.215),
        qfrc_inverse=vec(3.0, 4.0),
        nis=0.75,
        compute_us=120,
        receive_to_send_us=130,
    ),
    TickRecord(
        kind="rejected",
        seq=0,
        t=0.0,
        frame_qpos=vec(0.3, 0.4),
        reject_reason="TOO_OLD",
        reject_message="late",
    ),
]


def test_each_tick_holds_its_answer_when_due_its_correction_and_its_frame() -> None:
    timeline = session_timeline(pa.Table.from_batches([records_to_batch(RECORDS)]))
    assert timeline.seq.tolist() == [0, 1, 2]
    np.testing.assert_allclose(timeline.t, [0.0, 0.01, 0.02])
    assert timeline.source.tolist() == ["MEASURED", "PREDICTED", "PREDICTED"]
    assert timeline.corrected.tolist() == [False, True, False]
    assert timeline.gap.tolist() == [False, False, True]
    np.testing.assert_array_equal(timeline.answered_qpos, [[0.1, 0.2], [0.11, 0.21], [0.12, 0.22]])
    np.testing.assert_array_equal(timeline.corrected_qpos[1], [0.115, 0.215])
    assert np.isnan(timeline.corrected_qpos[[0, 2]]).all()
    np.testing.assert_array_equal(timeline.frame_qpos[:2], [[0.1, 0.2], [0.115, 0.215]])
    assert np.isnan(timeline.frame_qpos[2]).all()
    np.testing.assert_array_equal(timeline.answered_qfrc[:2], [[1.0, 2.0], [0.0, 0.0]])
    assert np.isnan(timeline.answered_qfrc[2]).all()  # not asked for on that tick
    np.testing.assert_array_equal(timeline.corrected_qfrc[1], [3.0, 4.0])
    # The frame's lateness whenever it came; the answer's timings of the answer sent when due.
    np.testing.assert_array_equal(timeline.frame_delay[:2], [0.004, 0.017])
    assert np.isnan(timeline.frame_delay[2])
    assert timeline.compute_us.tolist() == [40, 90, 80]
    assert timeline.receive_to_send_us.tolist() == [55, 95, 0]
    # NIS of the latest answer: the correction's for tick 1.
    np.testing.assert_array_equal(timeline.nis[:2], [1.5, 0.75])
    assert np.isnan(timeline.nis[2])
    rejected = timeline.rejections
    assert rejected.seq.tolist() == [0] and rejected.reason.tolist() == ["TOO_OLD"]
    np.testing.assert_array_equal(rejected.frame_qpos, [[0.3, 0.4]])
    assert np.isnan(rejected.frame_delay).all()


def test_a_session_of_rejections_only_has_no_ticks() -> None:
    timeline = session_timeline(pa.Table.from_batches([records_to_batch(RECORDS[4:])]))
    assert len(timeline.t) == 0 and timeline.answered_qpos.shape == (0, 0)
    assert timeline.rejections.reason.tolist() == ["TOO_OLD"]
