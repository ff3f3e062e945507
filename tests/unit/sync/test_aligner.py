"""The pose aligner: interpolation, slerp, gaps, latency compensation, bad poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundstation.sync import NoPose, Pose, PoseBuffer, slerp

MS = 1_000_000


def yaw_quat(yaw: float) -> np.ndarray:
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def test_linear_position_and_slerp_orientation_at_midpoint():
    buf = PoseBuffer(max_gap_ns=20 * MS)
    buf.insert(0, [0, 0, 0], yaw_quat(0.0))
    buf.insert(10 * MS, [1, 2, 3], yaw_quat(1.0))
    pose = buf.at(5 * MS)
    assert isinstance(pose, Pose)
    np.testing.assert_allclose(pose.position, [0.5, 1.0, 1.5])
    np.testing.assert_allclose(pose.quaternion, yaw_quat(0.5), atol=1e-12)
    assert pose.gap_ns == 10 * MS


def test_exact_hit_returns_the_stored_pose():
    buf = PoseBuffer()
    buf.insert(7, [1, 1, 1], yaw_quat(0.3))
    np.testing.assert_allclose(buf.at(7).position, [1, 1, 1])


def test_gap_larger_than_max_is_no_pose_with_reason():
    buf = PoseBuffer(max_gap_ns=20 * MS)
    buf.insert(0, [0, 0, 0], yaw_quat(0))
    buf.insert(30 * MS, [1, 0, 0], yaw_quat(0))
    result = buf.at(15 * MS)
    assert isinstance(result, NoPose) and result.reason == "gap" and result.gap_ns == 30 * MS
    assert not result


def test_outside_span_is_no_pose_unless_extrapolation_allowed():
    buf = PoseBuffer()
    assert buf.at(0).reason == "empty"
    buf.insert(10 * MS, [0, 0, 0], yaw_quat(0))
    buf.insert(15 * MS, [1, 0, 0], yaw_quat(0))
    assert buf.at(5 * MS).reason == "before"
    assert buf.at(20 * MS).reason == "after"
    hold = PoseBuffer(max_extrapolation_ns=6 * MS)
    hold.insert(10 * MS, [0, 0, 0], yaw_quat(0))
    np.testing.assert_allclose(hold.at(15 * MS).position, [0, 0, 0])
    assert hold.at(17 * MS).reason == "after"


def test_latency_compensation_shifts_pose_times():
    buf = PoseBuffer(latency_ns=4 * MS)
    buf.insert(10 * MS, [0, 0, 0], yaw_quat(0))
    buf.insert(20 * MS, [1, 0, 0], yaw_quat(0))
    # received at 10 and 20 ms -> vehicle was there at 6 and 16 ms
    np.testing.assert_allclose(buf.at(11 * MS).position, [0.5, 0, 0])


def test_bad_poses_are_rejected_and_counted():
    buf = PoseBuffer()
    assert buf.insert(0, [0, 0, 0], yaw_quat(0))
    assert not buf.insert(1, [np.nan, 0, 0], yaw_quat(0))
    assert not buf.insert(2, [0, 0, 0], [2.0, 0, 0, 0])
    assert not buf.insert(0, [0, 0, 0], yaw_quat(0))  # not after the newest
    assert buf.rejected == 3 and len(buf) == 1


def test_capacity_and_drop_before_keep_the_bracketing_pose():
    buf = PoseBuffer(capacity=5)
    for k in range(10):
        buf.insert(k * MS, [k, 0, 0], yaw_quat(0))
    assert len(buf) == 5
    buf.drop_before(7 * MS + 500_000)
    np.testing.assert_allclose(buf.at(7 * MS + 500_000).position, [7.5, 0, 0])


def test_slerp_takes_the_short_way_and_hits_the_ends():
    q0, q1 = yaw_quat(0.2), -yaw_quat(0.6)  # same rotation as yaw 0.6, opposite sign
    np.testing.assert_allclose(slerp(q0, q1, 0.5), yaw_quat(0.4), atol=1e-12)
    np.testing.assert_allclose(slerp(q0, q1, 0.0), q0, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(a=st.floats(-3, 3), b=st.floats(-3, 3), f=st.floats(0, 1))
def test_slerp_is_unit_and_monotone_in_angle(a, b, f):
    q = slerp(yaw_quat(a), yaw_quat(b), f)
    assert abs(np.linalg.norm(q) - 1) < 1e-9

    # angle travelled from q0 is f times the total (shortest) angle
    def angle(p, r):
        return 2 * math.acos(min(1.0, abs(float(np.dot(p, r)))))

    total = angle(yaw_quat(a), yaw_quat(b))
    assert angle(yaw_quat(a), q) == pytest.approx(f * total, abs=1e-6)


def test_bad_settings_raise():
    from groundstation.errors import InputDataError

    with pytest.raises(InputDataError, match="max_gap_ns"):
        PoseBuffer(max_gap_ns=0)
