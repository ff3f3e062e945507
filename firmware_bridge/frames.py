"""Axis conventions: the station's world frame, NED/ENU, FRD/FLU and Motive's frames.

The station's **world frame** is right-handed with z up and x, y horizontal (ENU-like:
x east, y north, z up). Quaternions here are Hamilton quaternions in **(w, x, y, z)** order
that rotate body-frame vectors into the reference frame (``v_ref = q * v_body * q^-1``), as
MAVLink's ATTITUDE_QUATERNION does for FRD -> NED. NatNet sends (x, y, z, w); the
conversions below take that order explicitly.

Motive Y-up (Motive's default) is right-handed with y up. Mapping it to the world frame::

    x_w = x_m,  y_w = -z_m,  z_w = y_m          R_wm = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]

det(R_wm) = +1: it is a proper rotation (+90 deg about x), so handedness is preserved
(x_m x y_m = z_m maps to x_w x z_w = -y_w, i.e. x_w x y_w = z_w). Motive Z-up is already
right-handed z-up and maps by identity. Orientations are re-expressed on both sides
(``q_w = q_wm * q_m * q_wm^-1``): a rigid body whose local axes coincide with Motive's axes
(Motive's default pivot at creation) comes out as identity in the world frame. In components
that is the same permutation as for positions: (qx, qy, qz) -> (qx, -qz, qy), qw unchanged.

All functions are pure and vectorised over leading axes: vectors (..., 3), quaternions (..., 4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from firmware_bridge.errors import BridgeError

Array = NDArray[np.float64]

_SQRT_HALF = float(np.sqrt(0.5))
#: Rotation NED -> ENU: 180 deg about (1, 1, 0)/sqrt(2); maps (n, e, d) to (e, n, -d).
Q_ENU_FROM_NED = np.array([0.0, _SQRT_HALF, _SQRT_HALF, 0.0])
#: Rotation FLU -> FRD: 180 deg about x; maps (f, l, u) to (f, -l, -u).
Q_FRD_FROM_FLU = np.array([0.0, 1.0, 0.0, 0.0])
#: Rotation Motive Y-up -> world: +90 deg about x.
Q_WORLD_FROM_MOTIVE_YUP = np.array([_SQRT_HALF, _SQRT_HALF, 0.0, 0.0])


class AxisError(BridgeError, ValueError):
    """An array has the wrong shape, a quaternion is zero or not finite, or a setting is bad."""


def _vec(v: ArrayLike, name: str, n: int = 3) -> Array:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != n:
        raise AxisError(
            f"{name} must have shape (..., {n}), got {a.shape}",
            hint="vectors are (..., 3) arrays, quaternions (..., 4)",
        )
    return a


def _quat(q: ArrayLike, name: str = "q") -> Array:
    """Validate and normalise a (..., 4) quaternion."""
    a = _vec(q, name, 4)
    norm = np.linalg.norm(a, axis=-1, keepdims=True)
    if not np.all(np.isfinite(norm)) or np.any(norm < 1e-12):
        raise AxisError(
            f"{name} contains a zero-length or non-finite quaternion",
            hint="a lost track may send zeros or NaN; drop that sample",
        )
    return a / norm


# --- vectors ----------------------------------------------------------------------------------


def enu_to_ned(v: ArrayLike) -> Array:
    """ENU vectors (east, north, up) to NED (north, east, down).

    Parameters
    ----------
    v : (..., 3) array_like

    Returns
    -------
    (..., 3) ndarray
    """
    a = _vec(v, "v")
    return np.stack([a[..., 1], a[..., 0], -a[..., 2]], axis=-1)


def ned_to_enu(v: ArrayLike) -> Array:
    """NED vectors (north, east, down) to ENU (east, north, up); the same involution."""
    a = _vec(v, "v")
    return np.stack([a[..., 1], a[..., 0], -a[..., 2]], axis=-1)


# --- quaternion algebra -----------------------------------------------------------------------


def quat_multiply(p: ArrayLike, q: ArrayLike) -> Array:
    """Hamilton product ``p * q`` of (..., 4) quaternions in (w, x, y, z) order (broadcasts)."""
    a = _vec(p, "p", 4)
    b = _vec(q, "q", 4)
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def quat_conjugate(q: ArrayLike) -> Array:
    """Conjugate (the inverse of a unit quaternion), (..., 4) in (w, x, y, z) order."""
    a = _vec(q, "q", 4)
    return a * np.array([1.0, -1.0, -1.0, -1.0])


def quat_from_axis_angle(axis: ArrayLike, angle_rad: ArrayLike) -> Array:
    """Unit quaternion (w, x, y, z) rotating by ``angle_rad`` (rad) about ``axis`` (..., 3)."""
    ax = _vec(axis, "axis")
    n = np.linalg.norm(ax, axis=-1, keepdims=True)
    if np.any(n < 1e-12) or not np.all(np.isfinite(n)):
        raise AxisError("axis must be a finite non-zero vector")
    half = 0.5 * np.asarray(angle_rad, dtype=np.float64)[..., None]
    return np.concatenate([np.cos(half), np.sin(half) * ax / n], axis=-1)


def quat_to_matrix(q: ArrayLike) -> Array:
    """Rotation matrices (..., 3, 3) of (..., 4) quaternions (w, x, y, z); normalises first."""
    w, x, y, z = np.moveaxis(_quat(q), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def rotate(q: ArrayLike, v: ArrayLike) -> Array:
    """Rotate (..., 3) vectors by (..., 4) quaternions: ``q * v * q^-1`` (broadcasts)."""
    qn = _quat(q)
    a = _vec(v, "v")
    w = qn[..., :1]
    u = qn[..., 1:]
    t = 2.0 * np.cross(u, a)
    return a + w * t + np.cross(u, t)


# --- attitude frames --------------------------------------------------------------------------


def quat_ned_frd_to_enu_flu(q: ArrayLike) -> Array:
    """Body FRD -> NED attitude (MAVLink) to body FLU -> ENU attitude.

    ``q_enu_flu = q_enu_ned * q_ned_frd * q_frd_flu`` (chain of frame changes). A level vehicle
    heading north (identity in NED/FRD) becomes a 90 deg yaw in ENU: its nose points +y.

    Parameters
    ----------
    q : (..., 4) array_like
        (w, x, y, z), rotates FRD body vectors into NED.

    Returns
    -------
    (..., 4) ndarray
        (w, x, y, z), rotates FLU body vectors into ENU. Sign is not canonicalised.
    """
    return quat_multiply(quat_multiply(Q_ENU_FROM_NED, _quat(q)), Q_FRD_FROM_FLU)


def quat_enu_flu_to_ned_frd(q: ArrayLike) -> Array:
    """Inverse of :func:`quat_ned_frd_to_enu_flu` (FLU -> ENU attitude to FRD -> NED)."""
    return quat_multiply(
        quat_multiply(quat_conjugate(Q_ENU_FROM_NED), _quat(q)), quat_conjugate(Q_FRD_FROM_FLU)
    )


# --- Motive -----------------------------------------------------------------------------------

Up = Literal["y", "z"]
Order = Literal["xyzw", "wxyz"]


def _check_up(up: str) -> None:
    if up not in ("y", "z"):
        raise AxisError(f"motive up axis must be 'y' or 'z', got {up!r}")


def motive_to_world(
    position: ArrayLike, orientation_xyzw: ArrayLike, up: Up = "y"
) -> tuple[Array, Array]:
    """Motive pose to the station's world frame.

    Parameters
    ----------
    position : (..., 3) array_like
        Metres in Motive's frame.
    orientation_xyzw : (..., 4) array_like
        Motive quaternion, (x, y, z, w) as on the NatNet wire.
    up : {"y", "z"}
        Motive's up axis setting.

    Returns
    -------
    position_w : (..., 3) ndarray
        Metres, world frame (z up).
    q_wxyz : (..., 4) ndarray
        Unit quaternion (w, x, y, z), body -> world (see the module docstring).
    """
    _check_up(up)
    p = _vec(position, "position")
    qm = _quat(orientation_xyzw, "orientation_xyzw")
    qx, qy, qz, qw = np.moveaxis(qm, -1, 0)
    if up == "y":  # x_w = x_m, y_w = -z_m, z_w = y_m, for positions and quaternion axes
        pw = np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)
        return pw, np.stack([qw, qx, -qz, qy], axis=-1)
    return p.copy(), np.stack([qw, qx, qy, qz], axis=-1)


def motive_pose_to_world(
    position: tuple[float, float, float],
    orientation: tuple[float, float, float, float],
    up: Up = "y",
    order: Order = "xyzw",
) -> tuple[tuple[float, float, float], tuple[float, float, float, float]] | None:
    """One Motive pose to the world frame in plain floats: :func:`motive_to_world` (after
    :meth:`AxisConvention.to_world`'s reordering) for a single pose, without numpy's per-call
    overhead (a NatNet stream decodes one such pose per rigid body per frame).

    The result is bit for bit the one of the array version: the norm sums the squares left to
    right, as numpy's reduction does over 4 contiguous elements (``tests/unit/firmware_bridge/
    test_frames.py`` checks it on random poses). None when the quaternion is zero, denormal or
    not finite (where the array version raises :class:`AxisError`).

    Parameters
    ----------
    position : (3,) floats
        Metres in Motive's frame.
    orientation : (4,) floats
        Motive quaternion in ``order``.
    up, order : see :class:`AxisConvention`
    """
    if order == "xyzw":
        qx, qy, qz, qw = orientation
    else:
        qw, qx, qy, qz = orientation
    norm = math.sqrt(((qx * qx + qy * qy) + qz * qz) + qw * qw)
    if not (math.isfinite(norm) and norm >= 1e-12):
        return None
    qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
    x, y, z = position
    if up == "y":
        return (x, -z, y), (qw, qx, -qz, qy)
    return (x, y, z), (qw, qx, qy, qz)


def world_to_motive(position: ArrayLike, q_wxyz: ArrayLike, up: Up = "y") -> tuple[Array, Array]:
    """Inverse of :func:`motive_to_world`: world pose to Motive position and (x, y, z, w)."""
    _check_up(up)
    p = _vec(position, "position")
    w, x, y, z = np.moveaxis(_quat(q_wxyz, "q_wxyz"), -1, 0)
    if up == "y":  # x_m = x_w, y_m = z_w, z_m = -y_w
        pm = np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)
        return pm, np.stack([x, z, -y, w], axis=-1)
    return p.copy(), np.stack([x, y, z, w], axis=-1)


@dataclass(frozen=True)
class AxisConvention:
    """The mocap axis settings, grouped (configured once, printed with the config).

    Attributes
    ----------
    motive_up : {"y", "z"}
        Motive's up axis.
    quaternion_order : {"xyzw", "wxyz"}
        Component order of incoming orientations (NatNet: "xyzw").
    """

    motive_up: Up = "y"
    quaternion_order: Order = "xyzw"

    def __post_init__(self) -> None:
        _check_up(self.motive_up)
        if self.quaternion_order not in ("xyzw", "wxyz"):
            raise AxisError(
                f"quaternion_order must be 'xyzw' or 'wxyz', got {self.quaternion_order!r}"
            )

    def to_world(self, position: ArrayLike, orientation: ArrayLike) -> tuple[Array, Array]:
        """Mocap pose (orientation in ``quaternion_order``) to world position and (w,x,y,z)."""
        q = _vec(orientation, "orientation", 4)
        if self.quaternion_order == "wxyz":
            q = np.roll(q, -1, axis=-1)
        return motive_to_world(position, q, self.motive_up)

    def to_motive(self, position: ArrayLike, q_wxyz: ArrayLike) -> tuple[Array, Array]:
        """World pose to mocap position and orientation in ``quaternion_order``."""
        p, q = world_to_motive(position, q_wxyz, self.motive_up)
        if self.quaternion_order == "wxyz":
            q = np.roll(q, 1, axis=-1)
        return p, q
