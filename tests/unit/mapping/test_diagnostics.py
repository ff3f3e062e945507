"""Fit diagnostics: each detection pinned on a small planted case (real fits where possible)."""

from __future__ import annotations

import types
import warnings

import numpy as np
import pytest

from groundstation.bench import shapes2d
from groundstation.mapping import GPIS, RobustGPIS
from groundstation.mapping.diagnostics import (
    FALLBACKS,
    FitDiagnosis,
    diagnose,
    fallback_params,
    final_elbo,
)
from groundstation.mapping.surface import SurfaceMesh


def _data(outlier_prob: float = 0.03, n_free: int = 150, seed: int = 0) -> shapes2d.Dataset:
    rng = np.random.default_rng(seed)
    return shapes2d.make_dataset(
        shapes2d.make_shape("circle"), rng, n_free=n_free, outlier_prob=outlier_prob,
        region_half=1.5,
    )  # fmt: skip


def _fit(model, d):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return model.fit(d.X, d.y)


@pytest.fixture(scope="module")
def good_robust():
    return _fit(RobustGPIS(), _data())


def test_a_good_robust_fit_is_reliable(good_robust):
    diag = diagnose(good_robust, surface=[np.zeros((5, 2))])
    assert diag.reliable, diag
    assert diag.reasons == () and diag.fallback == "none"
    assert diag.details["converged"] is True
    assert 0 < diag.details["flag_fraction"] < 0.3
    assert diag.summary() == "fit reliable"


def test_iteration_cap_is_reported_as_not_converged():
    m = _fit(RobustGPIS(max_iter=2), _data())
    assert not m.converged_
    diag = diagnose(m)
    assert not diag.reliable and "not_converged" in diag.reasons


def test_gpis_iteration_cap_is_reported_too():
    m = _fit(GPIS(max_iter=1), _data())
    assert "not_converged" in diagnose(m).reasons


def test_lengthscale_pinned_at_its_upper_bound():
    # The data want l ~ 0.5-0.8 m; a 0.1 m upper bound pins the fit there.
    m = _fit(RobustGPIS(lengthscale=0.05, lengthscale_bounds=(0.01, 0.1)), _data())
    assert m.lengthscale_ == pytest.approx(0.1, rel=0.01)
    diag = diagnose(m)
    assert "lengthscale_at_upper_bound" in diag.reasons
    assert diag.details["lengthscale_at_bound"] == "upper"


def test_a_configured_constraint_at_its_bound_is_not_a_failure():
    """The mapper's resolution floor / signal-variance cap are set on purpose: a fit resting
    on them is the constraint acting (listed in details), unlike a wide search bound."""
    m = _fit(RobustGPIS(lengthscale=0.05, lengthscale_bounds=(0.01, 0.1)), _data())
    diag = diagnose(m, constraints=("lengthscale_upper",))
    assert "lengthscale_at_upper_bound" not in diag.reasons
    assert diag.details["constrained"] == ["lengthscale_upper"]
    assert "lengthscale_at_upper_bound" in diagnose(m, constraints=("lengthscale_lower",)).reasons


def test_signal_variance_at_its_lower_bound():
    m = _fit(RobustGPIS(signal_var=2.0, signal_var_bounds=(1.9, 100.0)), _data())
    if m.signal_var_ > 1.9 * 1.01:
        pytest.skip(f"the fit moved sigma_f^2 to {m.signal_var_} (not the planted bound)")
    assert "signal_var_at_lower_bound" in diagnose(m).reasons


def test_gpis_noise_at_lower_bound_is_not_a_failure_but_upper_is():
    m = _fit(GPIS(), _data(outlier_prob=0.0))
    lo, hi = m.noise_var_bounds
    planted = types.SimpleNamespace(
        converged_=True, lengthscale_=0.5, lengthscale_bounds=(0.01, 100.0), signal_var_=1.0,
        signal_var_bounds=(1e-3, 1e3), noise_var_=lo, noise_var_bounds=(lo, hi),
    )  # fmt: skip
    assert diagnose(planted).reliable
    planted.noise_var_ = hi
    assert diagnose(planted).reasons == ("noise_var_at_upper_bound",)


def test_too_many_flagged_contacts():
    # A false contact 1 cm from every external point (labels 0 and +1 that cannot both hold)
    # with theta fixed at the paper's l = 0.25: the fit gives up on the contacts.
    d = _data(outlier_prob=0.0)
    ext = d.X[d.y == 1]
    fc = ext + np.random.default_rng(5).normal(0.0, 0.01, ext.shape)
    X, y = np.vstack([d.X, fc]), np.concatenate([d.y, np.zeros(len(fc))])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = RobustGPIS(optimize=False).fit(X, y)
    diag = diagnose(m)
    assert diag.details["flag_fraction"] > 0.3
    assert "too_many_flagged" in diag.reasons
    assert diag.fallback == "gpis_init"
    # The threshold is a setting.
    assert "too_many_flagged" not in diagnose(m, flag_fraction_max=1.0).reasons
    # A good fit of the same kind flags only the planted false contacts.
    assert "too_many_flagged" not in diagnose(_fit(RobustGPIS(optimize=False), d)).reasons


def test_alpha_on_the_gaussian_plateau_only_matters_when_outliers_are_expected(good_robust):
    planted = types.SimpleNamespace(**{k: getattr(good_robust, k) for k in (
        "converged_", "lengthscale_", "lengthscale_bounds", "signal_var_", "signal_var_bounds",
        "alpha_bounds", "beta_", "uncertainty_", "y_train_")})  # fmt: skip
    planted.alpha_ = 4e5  # on the plateau, below the 1e6 bound
    assert "alpha_at_upper_bound" in diagnose(planted).reasons
    assert diagnose(planted, outliers_expected=False).reliable
    planted.alpha_ = 0.4
    assert diagnose(planted).reliable


def test_restart_elbo_disagreement(good_robust):
    best = final_elbo(good_robust)
    assert np.isfinite(best)
    assert diagnose(good_robust, restarts=[best, best - 0.5]).reliable
    diag = diagnose(good_robust, restarts=[best, best - 0.5 * abs(best) - 10.0])
    assert "restart_elbo_disagreement" in diag.reasons
    assert diag.details["restart_elbo_spread"] > 10.0
    # Fitted estimators can be passed instead of numbers.
    other = _fit(RobustGPIS(max_iter=1), _data())
    d2 = diagnose(good_robust, restarts=[good_robust, other])
    assert d2.details["restart_elbos"][0] == pytest.approx(best)


def test_elbo_decrease_and_nonfinite_outputs(good_robust):
    planted = types.SimpleNamespace(converged_=True, elbo_trace_=[1.0, 5.0, 4.0])
    assert "elbo_decreased" in diagnose(planted).reasons
    planted = types.SimpleNamespace(converged_=True, lengthscale_=float("nan"))
    diag = diagnose(planted)
    assert "nonfinite_output" in diag.reasons and diag.details["nonfinite"] == ["lengthscale_"]
    field = np.zeros((4, 4))
    field[1, 2] = np.nan
    assert "nonfinite_output" in diagnose(good_robust, field=field).reasons


def test_empty_surface_in_2d_and_3d(good_robust):
    assert "empty_surface" in diagnose(good_robust, surface=[]).reasons
    assert "empty_surface" in diagnose(good_robust, surface=SurfaceMesh.empty()).reasons


def test_fallbacks(good_robust):
    planted = types.SimpleNamespace(converged_=False)
    d = diagnose(planted, have_last_good=True)
    assert d.fallback == "fixed_theta"
    params = fallback_params(d, {"lengthscale": 0.6, "signal_var": 2.0, "alpha": 0.4})
    assert params == {"lengthscale": 0.6, "signal_var": 2.0, "alpha": 0.4, "optimize": False}
    RobustGPIS(**params)  # valid keyword arguments
    d = diagnose(planted)  # nothing good to fall back on
    assert d.fallback == "gpis_init" and fallback_params(d)["init"] == "gpis"
    d = diagnose(good_robust, surface=[], have_last_good=True)
    assert d.fallback == "keep_last_mesh" and fallback_params(d) == {}
    assert set(FALLBACKS) == {"none", "keep_last_mesh", "fixed_theta", "gpis_init"}
    assert "unreliable" in d.summary() and d.fallback_text == FALLBACKS["keep_last_mesh"]


def test_wrappers_are_unwrapped(good_robust):
    wrapper = types.SimpleNamespace(fit_=good_robust, converged_=True)
    diag = diagnose(wrapper)
    assert isinstance(diag, FitDiagnosis) and diag.reliable
    assert diag.details["lengthscale"] == pytest.approx(good_robust.lengthscale_)
