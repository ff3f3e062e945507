"""Named causal low-pass filters for 3-vectors sampled at irregular times.

Both filters follow the data's clock: the moving average keeps the samples whose time lies in
``(t - window, t]``; the Butterworth filter is a 2nd-order section whose coefficients are derived
from the nominal sample interval and re-derived when the interval changes by more than 20 %. A
gap longer than ``reset_gap_s`` resets the filter, so stale history never leaks across a dropout.
"""

from __future__ import annotations

import collections
import math

import numpy as np


class MovingAverage:
    """Causal moving average over a time window.

    Parameters
    ----------
    window_s : float
        Window length, seconds.
    reset_gap_s : float
        A gap between samples longer than this clears the history.
    """

    name = "moving_average"

    def __init__(self, window_s: float, reset_gap_s: float = 0.5):
        self.window_ns = int(round(window_s * 1e9))
        self.reset_gap_ns = int(round(reset_gap_s * 1e9))
        self._buf: collections.deque[tuple[int, np.ndarray]] = collections.deque()
        self._sum = np.zeros(3)
        self._t_start: int | None = None
        self.ready = False

    def update(self, t_ns: int, v: np.ndarray) -> np.ndarray:
        if self._buf and t_ns - self._buf[-1][0] > self.reset_gap_ns:
            self.reset()
        if self._t_start is None:
            self._t_start = t_ns
        # Until a whole window has been seen the average is of too few samples (the first one
        # passes unfiltered): the detector must not arm on it.
        self.ready = t_ns - self._t_start >= self.window_ns
        self._buf.append((t_ns, v))
        self._sum = self._sum + v
        while self._buf and self._buf[0][0] <= t_ns - self.window_ns:
            self._sum = self._sum - self._buf.popleft()[1]
        if len(self._buf) == 1:  # re-anchor the running sum to avoid drift from round-off
            self._sum = self._buf[0][1].copy()
        return self._sum / len(self._buf)

    def reset(self) -> None:
        self._buf.clear()
        self._sum = np.zeros(3)
        self._t_start = None
        self.ready = False


class Butterworth2:
    """Causal 2nd-order Butterworth low-pass (bilinear transform, one biquad per axis).

    Parameters
    ----------
    cutoff_hz : float
        -3 dB frequency, Hz.
    reset_gap_s : float
        A gap between samples longer than this restarts the filter from the next sample.
    """

    name = "butterworth2"

    def __init__(self, cutoff_hz: float, reset_gap_s: float = 0.5):
        self.cutoff_hz = float(cutoff_hz)
        self.reset_gap_ns = int(round(reset_gap_s * 1e9))
        self._dt: float | None = None
        self._coef: tuple[np.ndarray, np.ndarray] | None = None
        self._t_prev: int | None = None
        self._x = [np.zeros(3), np.zeros(3)]
        self._y = [np.zeros(3), np.zeros(3)]
        self._t_start: int | None = None
        self.settle_ns = int(2e9 / self.cutoff_hz)  # about two time constants
        self.ready = False

    def _design(self, dt: float) -> None:
        fs = 1.0 / dt
        fc = min(self.cutoff_hz, 0.45 * fs)
        k = math.tan(math.pi * fc / fs)
        q = 1.0 / math.sqrt(2.0)
        norm = 1.0 / (1.0 + k / q + k * k)
        b0 = k * k * norm
        b = np.array([b0, 2 * b0, b0])
        a = np.array([1.0, 2 * (k * k - 1) * norm, (1 - k / q + k * k) * norm])
        self._coef = (b, a)
        self._dt = dt

    def update(self, t_ns: int, v: np.ndarray) -> np.ndarray:
        if self._t_prev is None or t_ns - self._t_prev > self.reset_gap_ns:
            self._t_prev = self._t_start = t_ns
            self.ready = False
            self._x = [v.copy(), v.copy()]
            self._y = [v.copy(), v.copy()]  # start at steady state: no start-up transient
            return v.copy()
        dt = max((t_ns - self._t_prev) * 1e-9, 1e-6)
        self._t_prev = t_ns
        self.ready = t_ns - self._t_start >= self.settle_ns
        if self._dt is None or abs(dt - self._dt) > 0.2 * self._dt:
            self._design(dt)
        b, a = self._coef
        y = b[0] * v + b[1] * self._x[0] + b[2] * self._x[1] - a[1] * self._y[0] - a[2] * self._y[1]
        self._x = [v, self._x[0]]
        self._y = [y, self._y[0]]
        return y

    def reset(self) -> None:
        self._t_prev = None
        self.ready = False


class Passthrough:
    """No filtering (for measurements that show why a filter is needed)."""

    name = "none"
    ready = True

    def update(self, t_ns: int, v: np.ndarray) -> np.ndarray:
        return v

    def reset(self) -> None:
        pass


def make_filter(name: str, window_s: float = 0.05, cutoff_hz: float = 8.0):
    """Build the filter named in the settings."""
    if name == "moving_average":
        return MovingAverage(window_s)
    if name == "butterworth2":
        return Butterworth2(cutoff_hz)
    if name == "none":
        return Passthrough()
    raise ValueError(f"unknown contact filter {name!r}; use moving_average, butterworth2 or none")
