"""Detect failed or suspicious implicit-surface fits, and say what to do about them (pure).

:func:`diagnose` inspects a fitted ``GPIS`` / ``RobustGPIS`` (or anything exposing the same fitted
attributes, e.g. a sparse estimator or a surface model wrapping one) and returns a
:class:`FitDiagnosis`. Checks, each with a stable reason string (ALGORITHM.md §7):

``not_converged``
    The EM (or the GPIS L-BFGS-B search) hit its iteration cap (§5, §7.9).
``elbo_decreased``
    The recorded ELBO L2 fell between iterations beyond rounding (§5: it must not).
``lengthscale_at_lower_bound`` / ``lengthscale_at_upper_bound`` / ``signal_var_at_*_bound``
    A kernel hyperparameter within ``bound_rtol`` (1 % in log) of its bound: at the upper
    length-scale bound the field is a constant function the EM never leaves (§7.2).
``noise_var_at_upper_bound``
    GPIS explains the data as noise (flat field). The lower bound is normal for interpolable
    labels (§7.7) and only reported in ``details``.
``alpha_at_upper_bound``
    The robust fit sits on the Gaussian plateau alpha -> inf (§7.3): no datum is down-weighted,
    i.e. no robustness, although outliers are expected (``outliers_expected``).
``too_many_flagged``
    More than ``flag_fraction_max`` of the contacts (y = 0; only contacts can be false,
    §7.5) have ``u_i > flag_u``: the model rejects the data instead of fitting it.
``restart_elbo_disagreement``
    Final ELBOs of several restarts (``restarts``) spread by more than ``elbo_rtol`` relative
    (§7.6): the fit depends on its start.
``nonfinite_output``
    NaN/inf in hyperparameters, uncertainties, the ELBO or the supplied field.
``empty_surface``
    The supplied mesh (3D) or contour list (2D) has no surface at all.

The recommended fallback (:data:`FALLBACKS`) is ordered by how cheap and safe it is: keep the last
good mesh while any reason stands; refit from the last good hyperparameters with theta fixed when
they exist and the failure is in the hyperparameter search; otherwise refit with the GPIS
initialisation (§7.2) from the paper's initial values. :func:`fallback_params` turns the
recommendation into estimator keyword overrides.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

#: Fallback keys and what they mean (the mapper applies them in this order of preference).
FALLBACKS: dict[str, str] = {
    "none": "the fit is reliable: publish its mesh",
    "keep_last_mesh": "keep the last good mesh; mark the new fit unreliable in status and "
    "recording",
    "fixed_theta": "keep the last good mesh and refit from the last good hyperparameters with "
    "theta fixed (optimize=False, warm alpha/beta)",
    "gpis_init": "keep the last good mesh and refit with init='gpis' from the paper's initial "
    "values (lengthscale 0.25, signal_var 1, direct (alpha, beta) update)",
}

#: Reasons caused by the hyperparameter search (fixing theta at a known-good value avoids them).
_THETA_REASONS = frozenset(
    {
        "not_converged",
        "lengthscale_at_lower_bound",
        "lengthscale_at_upper_bound",
        "signal_var_at_lower_bound",
        "signal_var_at_upper_bound",
        "noise_var_at_upper_bound",
        "alpha_at_upper_bound",
        "restart_elbo_disagreement",
        "elbo_decreased",
    }
)

#: Attribute names under which wrappers keep their inner fitted estimator.
_INNER = ("fit_", "estimator_", "model_", "gp_", "robust_", "_estimator")


@dataclasses.dataclass(frozen=True)
class FitDiagnosis:
    """Outcome of :func:`diagnose`.

    Attributes
    ----------
    reliable : bool
        True when no reason was found.
    reasons : tuple of str
        Reason strings (module docstring), in check order.
    details : dict
        Numbers behind the checks (hyperparameters, bound distances, flag fraction, ...).
    fallback : str
        Key of :data:`FALLBACKS` ("none" when reliable).
    """

    reliable: bool
    reasons: tuple[str, ...]
    details: dict
    fallback: str

    @property
    def fallback_text(self) -> str:
        """Human-readable fallback recommendation."""
        return FALLBACKS[self.fallback]

    def summary(self) -> str:
        """One line for a status display or a recording."""
        if self.reliable:
            return "fit reliable"
        return f"fit unreliable ({', '.join(self.reasons)}); fallback: {self.fallback}"


def _unwrap(est: Any) -> Any:
    """The object holding the fitted hyperparameters (the estimator or its inner one)."""
    if hasattr(est, "lengthscale_"):
        return est
    for name in _INNER:
        inner = getattr(est, name, None)
        if inner is not None and hasattr(inner, "lengthscale_"):
            return inner
    return est


def _num(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v


def _at_bound(value: float, bounds: Any, rtol: float) -> str | None:
    """'lower' / 'upper' when ``|log value - log bound| <= rtol`` (0.01: within 1 %)."""
    try:
        lo, hi = (float(b) for b in bounds)
    except (TypeError, ValueError):
        return None
    if not (value > 0 and lo > 0 and hi > lo):
        return None
    if math.log(value) - math.log(lo) <= rtol:  # within 1 % (in log) of the bound
        return "lower"
    if math.log(hi) - math.log(value) <= rtol:
        return "upper"
    return None


def final_elbo(est: Any) -> float:
    """Final ELBO of a robust fit, or the log marginal likelihood of a GPIS (nan if none)."""
    inner = _unwrap(est)
    trace = getattr(inner, "elbo_trace_", None)
    if trace is not None and len(trace):
        return float(trace[-1])
    lml = getattr(inner, "log_marginal_likelihood_", None)
    if lml is None:
        lml = getattr(inner, "elbo_", None)
    return float("nan") if lml is None else float(lml)


def _restart_values(restarts: Sequence[Any]) -> np.ndarray:
    vals = []
    for r in restarts:
        v = _num(r)
        vals.append(final_elbo(r) if v is None else v)
    return np.asarray(vals, dtype=np.float64)


def diagnose(
    estimator: Any,
    *,
    restarts: Sequence[Any] | None = None,
    flag_fraction_max: float = 0.3,
    flag_u: float = 0.01,
    outliers_expected: bool = True,
    bound_rtol: float = 0.01,
    alpha_plateau: float = 1e5,
    elbo_rtol: float = 0.05,
    elbo_atol: float = 5.0,
    surface: Any = None,
    field: np.ndarray | None = None,
    have_last_good: bool = False,
    constraints: Sequence[str] = (),
) -> FitDiagnosis:
    """Check a fitted estimator for non-convergence and suspicious fits.

    Parameters
    ----------
    estimator : fitted GPIS / RobustGPIS (or a wrapper, see ``_INNER``)
    restarts : sequence of float or fitted estimators, optional
        Final ELBOs (or fits) of restarts from other initial values; include this fit's if it
        should take part. Spread above ``max(elbo_atol, elbo_rtol * |best|)`` nats is suspicious.
    flag_fraction_max : float
        Largest acceptable fraction of contacts (y = 0) with ``u_i > flag_u``.
    flag_u : float
        Uncertainty u (label units^2) above which a datum counts as flagged. Genuine contacts sit
        near the beta floor (~1e-6) and false ones at 0.1-0.7 (ALGORITHM.md §7.4).
    outliers_expected : bool
        Whether alpha at its upper bound (no robustness) is a failure.
    bound_rtol : float
        Distance to a bound in log units counted as "at the bound" (0.01: within 1 %).
    alpha_plateau : float
        alpha at or above this (or at its upper bound) is the Gaussian plateau (§7.3); the
        direct update's bounded search stops anywhere on the flat profile, not exactly at
        the bound.
    elbo_rtol, elbo_atol : float
        Tolerances of the restart-ELBO spread (relative, nats).
    surface : SurfaceMesh, list of (k, 2) contours, or None
        The extracted surface; empty means the fit produced no surface.
    field : array, optional
        Grid values of the mean; any non-finite value is a failure.
    have_last_good : bool
        Whether the caller holds hyperparameters of an earlier reliable fit (selects the fallback).
    constraints : sequence of str
        Bounds set deliberately as modelling constraints, as ``"<name>_<lower|upper>"`` (e.g.
        ``"lengthscale_lower"`` for a configured resolution floor): a value there is the
        constraint acting, not a failed search; it is listed in ``details["constrained"]``.

    Returns
    -------
    FitDiagnosis
    """
    est = _unwrap(estimator)
    reasons: list[str] = []
    details: dict[str, Any] = {}
    nonfinite: list[str] = []

    converged = getattr(est, "converged_", getattr(estimator, "converged_", None))
    details["converged"] = None if converged is None else bool(converged)
    details["n_iter"] = _num(getattr(est, "n_iter_", None))
    if converged is not None and not converged:
        reasons.append("not_converged")

    trace = getattr(est, "elbo_trace_", None)
    if trace is not None and len(trace) > 1:
        tr = np.asarray(trace, dtype=np.float64)
        if not np.all(np.isfinite(tr)):
            nonfinite.append("elbo_trace_")
        else:
            drops = tr[:-1] - tr[1:]
            worst = float(drops.max())
            details["elbo_max_drop"] = worst
            if worst > 1e-6 * max(1.0, float(np.abs(tr).max())):
                reasons.append("elbo_decreased")

    for name, bound_attr in (
        ("lengthscale", "lengthscale_bounds"),
        ("signal_var", "signal_var_bounds"),
        ("noise_var", "noise_var_bounds"),
        ("alpha", "alpha_bounds"),
    ):
        value = _num(getattr(est, name + "_", None))
        if value is None:
            continue
        details[name] = value
        if not math.isfinite(value):
            nonfinite.append(name + "_")
            continue
        side = _at_bound(value, getattr(est, bound_attr, None), bound_rtol)
        details[name + "_at_bound"] = side
        if side is None and not (name == "alpha" and value >= alpha_plateau):
            continue
        if name == "noise_var" and side == "lower":
            continue  # interpolating GPIS: normal (ALGORITHM.md §7.7), kept in details only
        if f"{name}_{side}" in constraints:
            details.setdefault("constrained", []).append(f"{name}_{side}")
            continue
        if name == "alpha":
            if (side == "upper" or value >= alpha_plateau) and outliers_expected:
                reasons.append("alpha_at_upper_bound")
            continue
        reasons.append(f"{name}_at_{side}_bound")
    beta = _num(getattr(est, "beta_", None))
    if beta is not None:
        details["beta"] = beta
        if not math.isfinite(beta):
            nonfinite.append("beta_")

    u = getattr(est, "uncertainty_", None)
    if u is not None:
        u = np.asarray(u, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(u)):
            nonfinite.append("uncertainty_")
        elif getattr(est, "alpha_", None) is not None:  # u is a noise score only for robust fits
            y = getattr(est, "y_train_", None)
            contacts = (
                np.asarray(y).reshape(-1) == 0
                if y is not None and len(y) == len(u)
                else np.ones(len(u), bool)
            )
            if not np.any(contacts):
                contacts = np.ones(len(u), bool)
            frac = float(np.mean(u[contacts] > flag_u))
            details["flag_fraction"] = frac
            details["n_flagged"] = int(np.sum(u > flag_u))
            if frac > flag_fraction_max:
                reasons.append("too_many_flagged")

    if restarts is not None and len(restarts) >= 2:
        vals = _restart_values(restarts)
        details["restart_elbos"] = vals.tolist()
        if not np.all(np.isfinite(vals)):
            nonfinite.append("restart ELBO")
        else:
            spread = float(vals.max() - vals.min())
            details["restart_elbo_spread"] = spread
            if spread > max(elbo_atol, elbo_rtol * float(np.abs(vals).max())):
                reasons.append("restart_elbo_disagreement")

    if field is not None:
        f = np.asarray(field, dtype=np.float64)
        if not np.all(np.isfinite(f)):
            nonfinite.append("field")
    if nonfinite:
        details["nonfinite"] = nonfinite
        reasons.append("nonfinite_output")

    if surface is not None and _surface_empty(surface):
        reasons.append("empty_surface")

    reasons_t = tuple(dict.fromkeys(reasons))
    return FitDiagnosis(
        reliable=not reasons_t,
        reasons=reasons_t,
        details=details,
        fallback=_fallback(reasons_t, have_last_good),
    )


def _surface_empty(surface: Any) -> bool:
    if hasattr(surface, "is_empty"):
        return bool(surface.is_empty)
    if hasattr(surface, "faces"):
        return len(surface.faces) == 0
    if isinstance(surface, Sequence):
        return sum(len(c) for c in surface) < 2
    return False


def _fallback(reasons: tuple[str, ...], have_last_good: bool) -> str:
    if not reasons:
        return "none"
    if have_last_good and all(r in _THETA_REASONS for r in reasons):
        return "fixed_theta"
    if "too_many_flagged" in reasons or "nonfinite_output" in reasons or not have_last_good:
        return "gpis_init"
    return "keep_last_mesh"


def fallback_params(
    diagnosis: FitDiagnosis, last_good: Mapping[str, float] | None = None
) -> dict[str, Any]:
    """Estimator keyword overrides for the recommended refit ({} when none is needed).

    Parameters
    ----------
    diagnosis : FitDiagnosis
    last_good : mapping, optional
        Hyperparameters of the last reliable fit: ``lengthscale``, ``signal_var`` and, for a
        robust model, ``alpha``, ``beta``.

    Returns
    -------
    dict
        ``fixed_theta``: the last good values with ``optimize=False``; ``gpis_init``: the paper's
        initial values with ``init="gpis"`` and the direct noise update; otherwise ``{}``.
    """
    if diagnosis.fallback == "fixed_theta" and last_good:
        out: dict[str, Any] = {k: float(v) for k, v in last_good.items()}
        out["optimize"] = False
        return out
    if diagnosis.fallback == "gpis_init":
        return {
            "lengthscale": 0.25,
            "signal_var": 1.0,
            "init": "gpis",
            "noise_update": "direct",
            "warm_start": False,
        }
    return {}
