"""What the vehicle's IMU reports: specific force and rates in body FRD, with vibration and errors.

accel_FRD = C_FRD<-FLU R^T (a - g) + bias_a + vibration + noise_a     (specific force, m/s^2)
gyro_FRD  = C_FRD<-FLU omega_FLU + bias_g + noise_g                   (rad/s)

where C_FRD<-FLU = diag(1, -1, -1). Propeller vibration, aliased by 200 Hz sampling, is modelled
as a narrow-band oscillation whose aliased frequency follows the thrust (55-95 Hz, where a 50 ms
moving average of 10 samples suppresses it ~10x) plus broadband white noise, both scaled by
thrust / hover thrust and mostly along the thrust axis. Defaults reproduce real data
(external_data/aggressive_flight): an unfiltered 0.6 G threshold on | |a| - 1 G | fires on
~10-20 % of in-flight samples, the 50 ms average on ~0 %.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_bridge.sitl.physics import GRAVITY

_S = math.sqrt(0.5)
#: ENU -> NED: 180 deg about (1, 1, 0)/sqrt(2); FRD -> FLU: 180 deg about x (as in frames).
Q_NED_ENU = (0.0, _S, _S, 0.0)
Q_FLU_FRD = (0.0, 1.0, 0.0, 0.0)


def quat_mul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    """Hamilton product a (x) b of (w, x, y, z) quaternions (plain floats)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_enu_flu_to_ned_frd(q: tuple[float, ...]) -> tuple[float, float, float, float]:
    """Body FLU -> ENU quaternion to body FRD -> NED (PX4's ATTITUDE_QUATERNION), w >= 0.

    q_NED<-FRD = q_NED<-ENU (x) q_ENU<-FLU (x) q_FLU<-FRD; the same rotation as
    :func:`firmware_bridge.frames.quat_enu_flu_to_ned_frd` in plain floats (200 Hz hot path).
    """
    out = quat_mul(quat_mul(Q_NED_ENU, q), Q_FLU_FRD)
    return out if out[0] >= 0.0 else (-out[0], -out[1], -out[2], -out[3])


@dataclass(frozen=True)
class ImuParams:
    """IMU error model (per sample at the output rate; SI units)."""

    vib_amplitude: float = 4.0  # m/s^2, narrow-band, along body z at hover thrust
    vib_noise: float = 2.8  # m/s^2, broadband white, along body z at hover thrust
    vib_xy_ratio: float = 0.5  # horizontal vibration relative to vertical
    accel_noise: float = 0.05  # m/s^2, sensor white noise (always on)
    accel_bias: float = 0.08  # m/s^2, 1-sigma turn-on bias per axis
    gyro_noise: float = 0.004  # rad/s
    gyro_vibration: float = 0.03  # rad/s at hover thrust
    gyro_bias: float = 0.003  # rad/s, 1-sigma turn-on bias per axis


class ImuModel:
    """Turns true specific force / body rates into IMU samples (deterministic from ``rng``)."""

    _BLOCK = 2048

    def __init__(self, params: ImuParams, rng: np.random.Generator, hover_thrust: float):
        self.p = params
        self.rng = rng
        self.hover_thrust = hover_thrust
        self.accel_bias = tuple(float(v) for v in rng.normal(0.0, params.accel_bias, 3))
        self.gyro_bias = tuple(float(v) for v in rng.normal(0.0, params.gyro_bias, 3))
        self.phase = float(rng.random() * 2 * math.pi)
        self._buf: list[float] = []
        self._i = 0

    def _normals(self) -> list[float]:
        if self._i + 8 > len(self._buf):
            self._buf = self.rng.standard_normal(self._BLOCK * 8).tolist()
            self._i = 0
        i = self._i
        self._i += 8
        return self._buf[i : i + 8]

    def sample(
        self,
        f_world: tuple[float, float, float],
        rotation: tuple[float, ...],
        rates_flu: tuple[float, float, float],
        thrust: float,
        dt: float,
    ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """One IMU sample.

        Parameters
        ----------
        f_world : specific force (m/s^2, ENU), averaged over the sample interval.
        rotation : body FLU -> world ENU matrix, row-major 9-tuple.
        rates_flu : body rates (rad/s, FLU).
        thrust : N (vibration scales with thrust / hover thrust; none when the motors are off).
        dt : s since the previous sample (advances the vibration phase).

        Returns
        -------
        accel_frd : (3,) m/s^2, gyro_frd : (3,) rad/s
        """
        P = self.p
        R = rotation
        # R^T f -> body FLU
        bx = R[0] * f_world[0] + R[3] * f_world[1] + R[6] * f_world[2]
        by = R[1] * f_world[0] + R[4] * f_world[1] + R[7] * f_world[2]
        bz = R[2] * f_world[0] + R[5] * f_world[1] + R[8] * f_world[2]
        n = self._normals()
        s = max(0.0, thrust / self.hover_thrust)
        # Aliased blade-pass frequency follows thrust (Hz), drifting phase.
        freq = min(95.0, max(55.0, 75.0 + 30.0 * (s - 1.0)))
        self.phase = (self.phase + 2 * math.pi * freq * dt + 0.3 * n[7]) % (2 * math.pi)
        narrow = P.vib_amplitude * s * math.sin(self.phase)
        vz = narrow + P.vib_noise * s * n[0]
        vxy = P.vib_xy_ratio * s
        vx = vxy * (P.vib_amplitude * math.cos(self.phase + 0.7) * 0.5 + P.vib_noise * n[1])
        vy = vxy * (P.vib_amplitude * math.sin(self.phase + 1.9) * 0.5 + P.vib_noise * n[2])
        an = P.accel_noise
        ab = self.accel_bias
        accel = (
            bx + vx + ab[0] + an * n[3],
            -(by + vy) + ab[1] + an * n[4],
            -(bz + vz) + ab[2] + an * n[5],
        )
        gn = P.gyro_noise + P.gyro_vibration * s
        gb = self.gyro_bias
        m = self._normals()
        gyro = (
            rates_flu[0] + gb[0] + gn * m[0],
            -rates_flu[1] + gb[1] + gn * m[1],
            -rates_flu[2] + gb[2] + gn * m[2],
        )
        return accel, gyro


def detector_signal(accel: np.ndarray, window: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """The downstream detector's view of IMU samples: | |a| - 1 G |, raw and moving-averaged.

    Parameters
    ----------
    accel : (n, 3) m/s^2, specific force.
    window : samples in the moving average (10 = 50 ms at 200 Hz).

    Returns
    -------
    raw, filtered : (n,) in G; ``filtered`` averages |a| - 1 G over the trailing window before
    taking the absolute value (first ``window - 1`` entries are partial averages).
    """
    s = np.linalg.norm(np.asarray(accel, dtype=float), axis=1) / GRAVITY - 1.0
    c = np.cumsum(np.concatenate([[0.0], s]))
    idx = np.arange(1, len(s) + 1)
    lo = np.maximum(0, idx - window)
    avg = (c[idx] - c[lo]) / (idx - lo)
    return np.abs(s), np.abs(avg)
