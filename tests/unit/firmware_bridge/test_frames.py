"""Axis conventions: NED/ENU, FRD/FLU, Motive Y-up/Z-up, quaternion algebra."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from firmware_bridge.frames import (
    AxisConvention,
    AxisError,
    enu_to_ned,
    motive_pose_to_world,
    motive_to_world,
    ned_to_enu,
    quat_conjugate,
    quat_enu_flu_to_ned_frd,
    quat_from_axis_angle,
    quat_multiply,
    quat_ned_frd_to_enu_flu,
    quat_to_matrix,
    rotate,
    world_to_motive,
)

finite = st.floats(-1e3, 1e3, allow_nan=False)
vecs = arrays(np.float64, (5, 3), elements=finite)
quats = arrays(np.float64, (5, 4), elements=st.floats(-1, 1)).filter(
    lambda q: np.all(np.linalg.norm(q, axis=-1) > 0.1)
)
EX, EY, EZ = np.eye(3)


def _unit(q):
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _same_rotation(p, q):
    """Quaternions equal up to sign (q and -q are the same rotation)."""
    dot = np.abs(np.sum(_unit(np.asarray(p)) * _unit(np.asarray(q)), axis=-1))
    return np.allclose(dot, 1.0, atol=1e-9)


def test_enu_ned_known_vectors():
    assert np.array_equal(enu_to_ned([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])
    assert np.array_equal(ned_to_enu([[2.0, 1.0, -3.0]]), [[1.0, 2.0, 3.0]])


@given(vecs)
def test_enu_ned_round_trip(v):
    assert np.array_equal(ned_to_enu(enu_to_ned(v)), v)


def test_known_rotations():
    yaw90 = quat_from_axis_angle(EZ, np.pi / 2)
    assert np.allclose(rotate(yaw90, EX), EY)
    assert np.allclose(rotate(yaw90, EY), -EX)
    roll90 = quat_from_axis_angle(EX, np.pi / 2)
    assert np.allclose(rotate(roll90, EY), EZ)
    pitch90 = quat_from_axis_angle(EY, np.pi / 2)
    assert np.allclose(rotate(pitch90, EZ), EX)
    # composition: yaw then roll in the body frame = q_yaw * q_roll
    q = quat_multiply(yaw90, roll90)
    assert np.allclose(rotate(q, EY), rotate(yaw90, rotate(roll90, EY)))
    assert np.allclose(quat_to_matrix(yaw90), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


@given(quats, vecs)
@settings(max_examples=50)
def test_matrix_rotate_and_product_agree(q, v):
    m = quat_to_matrix(q)
    assert np.allclose(np.einsum("...ij,...j->...i", m, v), rotate(q, v), atol=1e-8)
    assert np.allclose(m @ np.swapaxes(m, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(m), 1.0)
    p = np.roll(q, 1, axis=0)
    assert np.allclose(rotate(quat_multiply(p, q), v), rotate(p, rotate(q, v)), atol=1e-7)
    assert np.allclose(rotate(quat_conjugate(q), rotate(q, v)), v, atol=1e-8)


def test_level_north_in_ned_points_plus_y_in_enu():
    """Identity FRD->NED (level, nose north) is a 90 deg yaw in ENU: the nose points +y."""
    q_enu = quat_ned_frd_to_enu_flu([1.0, 0.0, 0.0, 0.0])
    assert np.allclose(rotate(q_enu, EX), EY)  # forward -> north (+y)
    assert np.allclose(rotate(q_enu, EY), -EX)  # left -> west
    assert np.allclose(rotate(q_enu, EZ), EZ)  # up -> up
    assert _same_rotation(q_enu, quat_from_axis_angle(EZ, np.pi / 2))


def test_heading_east_in_ned_is_identity_in_enu():
    q_ned = quat_from_axis_angle(EZ, np.pi / 2)  # NED yaw +90 deg: nose east
    assert _same_rotation(quat_ned_frd_to_enu_flu(q_ned), [1.0, 0, 0, 0])


@given(quats, vecs)
@settings(max_examples=50)
def test_frd_ned_and_flu_enu_describe_the_same_physical_rotation(q_ned, v_flu):
    """Rotating a body vector in NED then converting equals converting then rotating in ENU."""
    q_enu = quat_ned_frd_to_enu_flu(q_ned)
    v_frd = v_flu * np.array([1.0, -1.0, -1.0])  # FLU -> FRD
    lhs = ned_to_enu(rotate(q_ned, v_frd))
    assert np.allclose(rotate(q_enu, v_flu), lhs, atol=1e-8)
    assert _same_rotation(quat_enu_flu_to_ned_frd(q_enu), q_ned)


def test_motive_y_up_mapping_and_handedness():
    p, q = motive_to_world([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0], up="y")
    assert np.array_equal(p, [1.0, -3.0, 2.0])  # x_w = x_m, y_w = -z_m, z_w = y_m
    assert np.array_equal(q, [1.0, 0.0, 0.0, 0.0])
    # The position map is a proper rotation: right-handed stays right-handed.
    r = np.stack([motive_to_world(e, [0, 0, 0, 1])[0] for e in np.eye(3)], axis=1)
    assert np.isclose(np.linalg.det(r), 1.0)
    assert np.allclose(np.cross(r[:, 0], r[:, 1]), r[:, 2])
    # Motive up (+y_m) is world up (+z_w).
    assert np.allclose(motive_to_world(EY, [0, 0, 0, 1])[0], EZ)


@given(vecs, quats)
@settings(max_examples=50)
def test_motive_orientation_is_conjugated_by_the_axis_map(p_body, q_xyzw):
    """Body vectors rotated in Motive then mapped equal mapped then rotated in the world."""
    q_m_wxyz = np.roll(q_xyzw, 1, axis=-1)
    for up in ("y", "z"):
        _, q_w = motive_to_world(np.zeros(3), q_xyzw, up=up)
        map_ = lambda v, up=up: motive_to_world(v, [0, 0, 0, 1], up=up)[0]  # noqa: E731
        lhs = map_(rotate(q_m_wxyz, p_body))
        rhs = rotate(q_w, map_(p_body))
        assert np.allclose(lhs, rhs, atol=1e-7)


@given(vecs, quats, st.sampled_from(["y", "z"]))
@settings(max_examples=50)
def test_motive_world_round_trip(p, q_xyzw, up):
    pw, qw = motive_to_world(p, q_xyzw, up=up)
    pm, qm = world_to_motive(pw, qw, up=up)
    assert np.allclose(pm, p)
    assert np.allclose(qm, _unit(q_xyzw))


def test_motive_z_up_is_identity_with_reordering():
    p, q = motive_to_world([1.0, 2.0, 3.0], [0.1, 0.2, 0.3, 0.9], up="z")
    assert np.array_equal(p, [1.0, 2.0, 3.0])
    assert np.allclose(q, _unit(np.array([0.9, 0.1, 0.2, 0.3])))


def test_axis_convention_orders_and_validation():
    yup = AxisConvention()
    assert (yup.motive_up, yup.quaternion_order) == ("y", "xyzw")
    p1, q1 = yup.to_world([1, 2, 3], [0.1, 0.2, 0.3, 0.9])
    p2, q2 = AxisConvention("y", "wxyz").to_world([1, 2, 3], [0.9, 0.1, 0.2, 0.3])
    assert np.allclose(p1, p2) and np.allclose(q1, q2)
    pm, qm = AxisConvention("y", "wxyz").to_motive(p2, q2)
    assert np.allclose(pm, [1, 2, 3]) and np.allclose(qm, _unit(np.array([0.9, 0.1, 0.2, 0.3])))
    with pytest.raises(AxisError, match="up"):
        AxisConvention("x")
    with pytest.raises(AxisError, match="quaternion_order"):
        AxisConvention("y", "zyxw")


def test_bad_input_is_named():
    with pytest.raises(AxisError, match=r"shape \(\.\.\., 3\)"):
        enu_to_ned([1.0, 2.0])
    with pytest.raises(AxisError, match="zero-length or non-finite"):
        rotate([0, 0, 0, 0], [1, 0, 0])
    with pytest.raises(AxisError, match="non-finite"):
        quat_to_matrix([np.nan, 0, 0, 1])
    with pytest.raises(AxisError, match="motive up"):
        motive_to_world([0, 0, 0], [0, 0, 0, 1], up="Y")
    with pytest.raises(AxisError):
        quat_from_axis_angle([0, 0, 0], 1.0)


@pytest.mark.parametrize("up", ["y", "z"])
@pytest.mark.parametrize("order", ["xyzw", "wxyz"])
def test_scalar_motive_pose_equals_the_array_version_bit_for_bit(up, order):
    # oracle: AxisConvention.to_world (numpy); the NatNet decoder runs the scalar one per body
    rng = np.random.default_rng(0)
    conv = AxisConvention(up, order)
    for _ in range(3000):
        scale = rng.choice([1.0, 1e-3, 1e3, 1e-5])
        p = tuple(rng.normal(size=3).astype(np.float32).astype(float) * 10)
        q = tuple((rng.normal(size=4) * scale).astype(np.float32).astype(float))
        pw, qw = conv.to_world(p, q)
        got = motive_pose_to_world(p, q, up, order)
        assert got is not None
        assert np.array(got[0]).tobytes() == pw.tobytes()
        assert np.array(got[1]).tobytes() == qw.tobytes()
    for bad in [(0.0, 0.0, 0.0, 0.0), (np.nan, 0.0, 0.0, 1.0), (np.inf, 0.0, 0.0, 1.0)]:
        with pytest.raises(AxisError):
            conv.to_world((0.0, 0.0, 0.0), bad)
        assert motive_pose_to_world((0.0, 0.0, 0.0), bad, up, order) is None
