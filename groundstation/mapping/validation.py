"""Input and settings checks shared by the GPIS estimators.

Bad data raises :class:`InputDataError` naming the problem (and the offending rows); bad settings
raise :class:`ConfigError` naming the setting. Both are raised from ``fit``/``predict``, never
from ``__init__`` (scikit-learn convention).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from groundstation.errors import ConfigError, InputDataError, NotFittedError

_MAX_ROWS_SHOWN = 10


def _rows(bad: np.ndarray) -> str:
    idx = np.flatnonzero(bad)
    shown = ", ".join(str(int(i)) for i in idx[:_MAX_ROWS_SHOWN])
    more = f" and {idx.size - _MAX_ROWS_SHOWN} more" if idx.size > _MAX_ROWS_SHOWN else ""
    return f"[{shown}{more}]"


def _as_float_array(value: object, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputDataError(f"{name} must be numeric, got {type(value).__name__}: {exc}") from exc
    return arr


def check_inputs(X: object, name: str = "X", dims: Sequence[int] = (2, 3)) -> np.ndarray:
    """Validate an input array of points.

    Parameters
    ----------
    X : array-like, (n, d) with d in ``dims``, metres
    name : str
        Name used in messages.
    dims : sequence of int
        Allowed dimensions d.

    Returns
    -------
    X : (n, d) float64, C-contiguous copy-or-view
    """
    X = _as_float_array(X, name)
    if X.ndim != 2:
        raise InputDataError(
            f"{name} must be a 2-D array of shape (n, d), got shape {X.shape}",
            hint="one point per row, columns x, y[, z] in metres",
        )
    if X.shape[1] not in dims:
        allowed = " or ".join(str(d) for d in dims)
        raise InputDataError(f"{name} must have {allowed} columns (dims), got {X.shape[1]}")
    if X.shape[0] == 0:
        raise InputDataError(f"{name} is empty (0 rows)")
    bad = ~np.isfinite(X).all(axis=1)
    if bad.any():
        raise InputDataError(f"{name} contains NaN or inf in rows {_rows(bad)}")
    return np.ascontiguousarray(X)


def check_training_data(X: object, y: object) -> tuple[np.ndarray, np.ndarray]:
    """Validate a training set (ALGORITHM.md §1).

    Parameters
    ----------
    X : array-like, (n, 2) or (n, 3), metres
    y : array-like, (n,)
        Labels (-1 inside, 0 surface, +1 outside; any finite float accepted).

    Returns
    -------
    X : (n, d) float64
    y : (n,) float64

    Raises
    ------
    InputDataError
        Wrong shapes or dims, empty, n < 2, length mismatch, NaN/inf (rows named), or no
        contact (no y == 0).
    """
    X = check_inputs(X, "X")
    y = _as_float_array(y, "y")
    if y.ndim != 1:
        raise InputDataError(f"y must be a 1-D array of shape (n,), got shape {y.shape}")
    if y.shape[0] != X.shape[0]:
        raise InputDataError(
            f"X and y lengths differ: X has {X.shape[0]} rows, y has {y.shape[0]} entries"
        )
    if X.shape[0] < 2:
        raise InputDataError(f"need at least 2 training points, got n = {X.shape[0]}")
    bad = ~np.isfinite(y)
    if bad.any():
        raise InputDataError(f"y contains NaN or inf in rows {_rows(bad)}")
    if not np.any(y == 0.0):
        raise InputDataError(
            "no contact in the training set (no y == 0): the surface is undefined",
            hint="add at least one contact point with label 0",
        )
    return X, np.ascontiguousarray(y)


def check_positive(name: str, value: object) -> float:
    """Return ``value`` as float if finite and > 0, else raise ConfigError."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name} must be a number > 0, got {value!r}") from exc
    if not (np.isfinite(v) and v > 0):
        raise ConfigError(f"{name} must be finite and > 0, got {value!r}")
    return v


def check_finite(name: str, value: object) -> float:
    """Return ``value`` as float if finite, else raise ConfigError."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name} must be a finite number, got {value!r}") from exc
    if not np.isfinite(v):
        raise ConfigError(f"{name} must be finite, got {value!r}")
    return v


def check_int(name: str, value: object, minimum: int) -> int:
    """Return ``value`` as int if it is an integer >= ``minimum``, else raise ConfigError."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def check_bounds(name: str, bounds: object, value: float, value_name: str) -> tuple[float, float]:
    """Check ``0 < lo <= hi`` and that the initial ``value`` lies within them."""
    try:
        lo, hi = (float(b) for b in bounds)  # type: ignore[union-attr]
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name} must be a pair (low, high), got {bounds!r}") from exc
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi):
        raise ConfigError(f"{name} must satisfy 0 < low <= high, got {bounds!r}")
    if not lo <= value <= hi:
        raise ConfigError(
            f"{value_name}={value!r} lies outside {name}={bounds!r}",
            hint=f"choose {value_name} within the bounds or widen them",
        )
    return lo, hi


def check_choice(name: str, value: object, choices: Sequence[str]) -> str:
    """Return ``value`` if it is one of ``choices``, else raise ConfigError."""
    if value not in choices:
        raise ConfigError(f"unknown {name} {value!r}; expected one of {', '.join(choices)}")
    return str(value)


def check_fitted(estimator: object, attribute: str = "posterior_") -> None:
    """Raise NotFittedError if ``estimator`` has not been fitted."""
    if getattr(estimator, attribute, None) is None:
        raise NotFittedError(
            f"this {type(estimator).__name__} is not fitted yet",
            hint="call fit(X, y) before predict",
        )
