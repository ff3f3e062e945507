"""Event-mixture GPIS: oracles (dense GP, explicit leave-burst-out refits) and the decisions it
must make on planted cases."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from groundstation.contact.detector import Observation
from groundstation.errors import InputDataError
from groundstation.mapping.kernels import se_kernel, se_mixed
from groundstation.mapping.mixture import EventMixtureGPIS, Groups, KernelBounds
from groundstation.mapping.training import TrainingPolicy, _plane_keep, build_training_set

BOUNDS = KernelBounds((0.1, 0.5), (0.05, 1.0))


def dense_gp(X, y, s2, Xq, ell, sf2, mu0=0.0):
    """Textbook GP mean and covariance with per-row noise (np.linalg.solve)."""
    K = se_kernel(X, X, ell, sf2)
    C = K + np.diag(s2)
    Kq = se_kernel(Xq, X, ell, sf2)
    mean = mu0 + Kq @ np.linalg.solve(C, y - mu0)
    cov = se_kernel(Xq, Xq, ell, sf2) - Kq @ np.linalg.solve(C, Kq.T)
    return mean, cov


def toy(seed=0, n_free=60):
    """A flat wall x = 0 (contacts + internal points, one event each), free points in front."""
    rng = np.random.default_rng(seed)
    X, y, g = [], [], []
    for e in range(12):
        c = np.array([0.0, rng.uniform(0, 1.5), rng.uniform(0, 1.5)])
        X += [c, c - [0.1, 0, 0]]
        y += [0.0, -0.5]
        g += [e, e]
    for _ in range(n_free):
        X.append([rng.uniform(0.3, 1.0), rng.uniform(-0.2, 1.7), rng.uniform(-0.2, 1.7)])
        y.append(1.0)
        g.append(-1)
    return np.array(X), np.array(y), np.array(g)


def toy_with_event(point, seed=0, n_free=60):
    """``toy`` and event 12: a contact at ``point`` with its internal point 0.1 m behind (-x);
    returns X, y, g and the rows' noise variances (free 0.3^2, contact and internal 0.05^2)."""
    X, y, g = toy(seed, n_free)
    point = np.asarray(point, float)
    X = np.vstack([X, point, point - [0.1, 0, 0]])
    y = np.concatenate([y, [0.0, -0.5]])
    g = np.concatenate([g, [12, 12]])
    return X, y, g, np.where(g < 0, 0.09, 0.0025)


def groups(g, prior, burst=None, extra=None):
    G = int(g.max()) + 1
    return Groups(
        row_group=g,
        prior_false=np.full(G, prior) if np.isscalar(prior) else np.asarray(prior, float),
        burst=np.arange(G) if burst is None else np.asarray(burst),
        extra_llr=np.zeros(G) if extra is None else np.asarray(extra, float),
    )


def test_with_every_event_trusted_it_is_the_plain_gp():
    X, y, g = toy()
    s2 = np.where(g < 0, 0.09, 0.0025)
    est = EventMixtureGPIS(lengthscale=0.3, signal_var=0.6, bounds=BOUNDS, learn_kernel=False)
    est.fit(X, y, s2, groups(g, 1e-6))
    Xq = np.random.default_rng(1).uniform(-0.2, 1.0, (40, 3))
    mean, cov = dense_gp(X, y, s2, Xq, 0.3, 0.6)
    m, s = est.predict(Xq, return_std=True)
    assert np.allclose(m, mean, atol=1e-8)
    assert np.allclose(s, np.sqrt(np.maximum(np.diag(cov), 0)), atol=1e-7)


def test_prediction_with_tangent_rows_is_the_dense_gp_over_values_and_slopes():
    """Oracle for ``MixedPosterior.predict`` (its own kernel expansion, value columns first):
    the textbook GP on the joint value/derivative covariance of ``kernels.se_mixed``."""
    X, y, g = toy()
    s2 = np.where(g < 0, 0.09, 0.0025)
    wall = np.flatnonzero(y == 0.0)[:6]  # slope rows interleaved with the value rows
    V = np.zeros_like(X)
    Xa = np.vstack([X, X[wall], X[wall]])
    Va = np.vstack([V, np.tile([0.0, 1.0, 0.0], (6, 1)), np.tile([0.0, 0.0, 1.0], (6, 1))])
    ya = np.concatenate([y, np.zeros(12)])
    s2a = np.concatenate([s2, np.full(12, 0.04)])
    ga = np.concatenate([g, g[wall], g[wall]])
    perm = np.random.default_rng(3).permutation(len(ya))
    Xa, Va, ya, s2a, ga = Xa[perm], Va[perm], ya[perm], s2a[perm], ga[perm]
    est = EventMixtureGPIS(
        lengthscale=0.3, signal_var=0.6, bounds=BOUNDS, learn_kernel=False, prior_mean=0.4
    )
    est.fit(Xa, ya, s2a, groups(ga, 1e-6), directions=Va)
    Xq = np.random.default_rng(1).uniform(-0.2, 1.0, (40, 3))
    Vq = np.zeros_like(Xq)
    C = se_mixed(Xa, Va, Xa, Va, 0.3, 0.6) + np.diag(s2a)
    Kq = se_mixed(Xq, Vq, Xa, Va, 0.3, 0.6)
    mu0 = np.where(np.einsum("ij,ij->i", Va, Va) > 0, 0.0, 0.4)  # a slope's prior mean is 0
    mean = 0.4 + Kq @ np.linalg.solve(C, ya - mu0)
    var = 0.6 - np.einsum("ij,ji->i", Kq, np.linalg.solve(C, Kq.T))
    m, s = est.predict(Xq, return_std=True)
    assert np.allclose(m, mean, atol=1e-8)
    assert np.allclose(s, np.sqrt(np.maximum(var, 0)), atol=1e-7)


def test_leave_burst_out_residuals_equal_an_explicit_refit_without_the_burst():
    X, y, g = toy()
    s2 = np.where(g < 0, 0.09, 0.0025)
    burst = np.array([0, 0, 0, 1, 1, 2, 3, 4, 5, 6, 7, 8])
    est = EventMixtureGPIS(
        lengthscale=0.3, signal_var=0.6, bounds=BOUNDS, learn_kernel=False, max_iter=1
    )
    est.fit(X, y, s2, groups(g, 1e-6, burst=burst))
    # the llr of group 0 from leaving out groups 0-2 (its burst) by hand
    out = np.isin(g, [0, 1, 2])
    keep = ~out
    r = 1e-4  # the priors are clipped there: the rest's rows carry that mixture noise
    s2_eff = np.where(g < 0, s2, 1.0 / ((1 - r) / s2 + r / est.outlier_var))
    mean, cov = dense_gp(X[keep], y[keep], s2_eff[keep], X[g == 0], 0.3, 0.6)
    e = float((y[g == 0] - mean).mean())  # the group's mean residual, its latent variance
    v = float(cov.mean())

    def logn(e, var):
        return -0.5 * (e * e / var + math.log(var) + math.log(2 * math.pi))

    llr = logn(e, v + est.outlier_var) - logn(e, v + s2[g == 0].mean())
    assert est.llr_[0] == pytest.approx(llr, rel=1e-6, abs=1e-6)


def test_a_companion_is_left_out_with_its_event_and_stays_in_the_fit():
    """Oracle: a burst's llr with a companion row is the explicit refit without the burst and
    the companion; the fitted surface (the decisions alike) does not change."""
    X, y, g, s2 = toy_with_event([0.0, 0.7, 0.7])
    X = np.vstack([X, [0.05, 0.7, 0.7]])  # the vehicle's centre as it met the wall
    y = np.append(y, 1.0)
    g = np.append(g, -1)
    s2 = np.append(s2, 0.09)
    comp = np.where(np.arange(len(g)) == len(g) - 1, 12, -1)
    base = groups(g, 1e-6)
    kw = dict(lengthscale=0.3, signal_var=0.6, bounds=BOUNDS, learn_kernel=False, max_iter=1)
    plain = EventMixtureGPIS(**kw).fit(X, y, s2, base)
    est = EventMixtureGPIS(**kw).fit(X, y, s2, dataclasses.replace(base, companion=comp))
    out = (g == 12) | (comp == 12)
    r = 1e-4
    s2_eff = np.where(g < 0, s2, 1.0 / ((1 - r) / s2 + r / est.outlier_var))
    mean, cov = dense_gp(X[~out], y[~out], s2_eff[~out], X[g == 12], 0.3, 0.6)
    e = float((y[g == 12] - mean).mean())
    v = float(cov.mean())

    def logn(e, var):
        return -0.5 * (e * e / var + math.log(var) + math.log(2 * math.pi))

    llr = logn(e, v + est.outlier_var) - logn(e, v + s2[g == 12].mean())
    assert est.llr_[12] == pytest.approx(llr, rel=1e-6, abs=1e-6)
    assert est.llr_[12] < plain.llr_[12]  # the +1 5 cm off no longer speaks against it
    np.testing.assert_allclose(np.delete(est.llr_, 12), np.delete(plain.llr_, 12), atol=1e-9)
    Xq = np.random.default_rng(1).uniform(-0.2, 1.0, (40, 3))
    np.testing.assert_allclose(est.predict(Xq), plain.predict(Xq), atol=1e-10)


def test_a_companion_must_be_a_trusted_row_of_an_existing_group():
    X, y, g = toy()
    base = groups(g, 0.1)
    with pytest.raises(InputDataError, match="companion"):
        dataclasses.replace(base, companion=np.where(g >= 0, 0, -1))  # a group's own row
    with pytest.raises(InputDataError, match="companion"):
        dataclasses.replace(base, companion=np.full(len(g), 99))
    with pytest.raises(InputDataError, match="companion"):
        dataclasses.replace(base, companion=np.zeros(3, dtype=np.int64))


def test_a_false_contact_in_free_space_is_flagged_and_a_doubted_touch_on_the_wall_is_not():
    # event 12: a 'contact' in the middle of the free points; event 0 doubted by its prior
    X, y, g, s2 = toy_with_event([0.6, 0.7, 0.7])
    prior = np.full(13, 0.1)
    prior[0] = 0.8
    est = EventMixtureGPIS(lengthscale=0.3, signal_var=0.6, bounds=BOUNDS)
    est.fit(X, y, s2, groups(g, prior))
    assert est.posterior_false_[12] > 0.9
    assert est.posterior_false_[0] < 0.5
    assert est.fit_.converged and est.fit_.n_flagged == 1


def thin_wall(thickness=0.2, seed=0):
    """A wall x in [0, thickness] touched at five spots from both sides (one event per touch,
    internal points 0.1 m behind), free points in front of both faces, and a false contact in
    free space (the last group)."""
    rng = np.random.default_rng(seed)
    X, y, g = [], [], []
    for _ in range(5):
        yz = [rng.uniform(0, 1.5), rng.uniform(0, 1.5)]
        for side, inward in ((0.0, 1.0), (thickness, -1.0)):
            c = np.array([side, *yz])
            X += [c, c + [0.1 * inward, 0, 0]]
            y += [0.0, -0.5]
            g += [len(g) // 2, len(g) // 2]
    for _ in range(80):
        x = thickness / 2 + rng.choice([-1, 1]) * (thickness / 2 + rng.uniform(0.2, 0.5))
        X.append([x, rng.uniform(-0.2, 1.7), rng.uniform(-0.2, 1.7)])
        y.append(1.0)
        g.append(-1)
    fake = np.array([-0.5, 0.7, 0.7])
    X += [fake, fake + [0.1, 0, 0]]
    y += [0.0, -0.5]
    g += [10, 10]
    return np.array(X), np.array(y), np.array(g)


def test_touches_the_kernel_is_too_smooth_for_are_not_taken_for_gusts():
    # with l = 0.35 m the model cannot fold a 0.2 m wall: each touch, left out, is predicted
    # inside by the touch on the other face. That is no evidence of a gust (whose point lies
    # in free space, where the vehicle flew); only the planted one in free space is false.
    X, y, g = thin_wall()
    s2 = np.where(g < 0, 0.09, 0.0025)

    def fit(flag_inside):
        est = EventMixtureGPIS(lengthscale=0.35, signal_var=0.5, bounds=BOUNDS,
                               learn_kernel=False, flag_inside=flag_inside)  # fmt: skip
        return est.fit(X, y, s2, groups(g, 0.1)).posterior_false_

    assert np.sum(fit(True)[:10] > 0.5) >= 2  # the old rule drops real touches
    post = fit(False)
    assert np.all(post[:10] <= 0.1 + 1e-9) and post[10] > 0.5


def test_a_lone_touch_with_nothing_against_it_keeps_its_prior():
    X, y, g, s2 = toy_with_event([3.0, 3.0, 3.0])  # nothing within metres
    est = EventMixtureGPIS(lengthscale=0.3, signal_var=0.6, bounds=BOUNDS)
    est.fit(X, y, s2, groups(g, 0.1))
    assert est.posterior_false_[12] < 0.5


@pytest.mark.parametrize("decide_p", [0.5, 0.25])
def test_the_decision_threshold_decides_fit_and_flags_alike(decide_p):
    """A lone event whose posterior stays near its prior of 0.45 is kept at 1/2 and decided false,
    left out of the fit and counted flagged, at 1/4; the wall's touches are kept either way."""
    far = np.array([3.0, 3.0, 3.0])
    X, y, g, s2 = toy_with_event(far)
    prior = np.r_[np.full(12, 0.01), 0.45]
    est = EventMixtureGPIS(
        lengthscale=0.3, signal_var=0.6, bounds=BOUNDS, learn_kernel=False, decide_p=decide_p
    )
    est.fit(X, y, s2, groups(g, prior))
    p = est.posterior_false_[12]
    assert 0.25 < p < 0.5
    lone = g == 12
    false = decide_p < p
    assert np.allclose(est.weights_[lone], 1e-4 if false else 1.0 / 0.0025, rtol=1e-6)
    assert est.fit_.n_flagged == int(false)
    inside = est.predict((far - [0.1, 0, 0])[None, :])[0]  # its internal point, label -0.5
    assert (abs(inside) < 0.05) if false else (inside < -0.4)
    assert np.all(est.posterior_false_[:12] < 0.05)


def test_the_decision_threshold_must_be_a_probability():
    with pytest.raises(InputDataError, match="decide_p"):
        EventMixtureGPIS(lengthscale=0.3, signal_var=0.6, bounds=BOUNDS, decide_p=1.0)


def test_each_group_is_decided_on_its_own_line():
    """The lone doubted event of the test above (posterior about its prior, 0.45) on a line of
    its own: 0.25 decides it false (left out, flagged) under an estimator whose line is 1/2,
    whatever that line; the wall's touches stay on theirs."""
    far = np.array([3.0, 3.0, 3.0])
    X, y, g, s2 = toy_with_event(far)
    prior = np.r_[np.full(12, 0.01), 0.45]
    own = dataclasses.replace(groups(g, prior), decide_p=np.r_[np.full(12, 0.5), 0.25])
    est = EventMixtureGPIS(lengthscale=0.3, signal_var=0.6, bounds=BOUNDS, learn_kernel=False)
    est.fit(X, y, s2, own)
    assert 0.25 < est.posterior_false_[12] < 0.5
    assert est.fit_.n_flagged == 1
    np.testing.assert_allclose(est.weights_[g == 12], 1e-4, rtol=1e-6)
    assert abs(est.predict((far - [0.1, 0, 0])[None, :])[0]) < 0.05  # nothing drawn there
    same = EventMixtureGPIS(lengthscale=0.3, signal_var=0.6, bounds=BOUNDS, learn_kernel=False)
    same.fit(X, y, s2, dataclasses.replace(own, decide_p=np.full(13, 0.5)))
    assert same.fit_.n_flagged == 0  # one line of 1/2 for all: the estimator's own
    with pytest.raises(InputDataError, match="decide_p"):
        dataclasses.replace(own, decide_p=np.full(12, 0.5))  # one line per group
    with pytest.raises(InputDataError, match="decide_p"):
        dataclasses.replace(own, decide_p=np.r_[np.full(12, 0.5), 1.0])


def test_a_cluster_cannot_vouch_for_itself_when_left_out_as_a_burst():
    X, y, g = toy(n_free=0)
    rng = np.random.default_rng(3)
    spot = np.array([0.7, 0.7, 0.7])
    rows, labs, grp = [], [], []
    for k in range(8):  # 8 consistent false contacts at one spot, events 12..19
        c = spot + rng.normal(0, 0.01, 3)
        rows += [c, c - [0.1, 0, 0]]
        labs += [0.0, -0.5]
        grp += [12 + k, 12 + k]
    # a free-space pass through the spot (the drone flew there before)
    path = [spot + [dx, 0.0, 0.0] for dx in np.linspace(-0.2, 0.3, 6)]
    X = np.vstack([X, rows, path])
    y = np.concatenate([y, labs, np.ones(len(path))])
    g = np.concatenate([g, grp, -np.ones(len(path), int)])
    s2 = np.where(g < 0, 0.09, 0.0025)
    burst_single = np.arange(20)
    burst_joint = np.concatenate([np.arange(12), np.full(8, 12)])
    est = EventMixtureGPIS(lengthscale=0.3, signal_var=0.6, bounds=BOUNDS, learn_kernel=False)
    alone = est.fit(X, y, s2, groups(g, 0.1, burst=burst_single)).posterior_false_[12:]
    joint = est.fit(X, y, s2, groups(g, 0.1, burst=burst_joint)).posterior_false_[12:]
    assert np.all(joint > 0.5)  # left out together, the path refutes them
    assert np.mean(alone > 0.5) < np.mean(joint > 0.5)  # one by one they vouch for each other


def test_kernel_learning_stays_in_its_bounds():
    X, y, g = toy()
    s2 = np.where(g < 0, 0.09, 0.0025)
    tight = KernelBounds((0.2, 0.25), (0.3, 0.4))
    est = EventMixtureGPIS(lengthscale=1.0, signal_var=5.0, bounds=tight)
    est.fit(X, y, s2, groups(g, 0.1))
    assert 0.2 <= est.lengthscale_ <= 0.25 and 0.3 <= est.signal_var_ <= 0.4


def obs(i, t, x, label, event, p=math.nan):
    return Observation(i, int(t * 1e9), np.asarray(x, float), float(label), np.zeros(3), event,
                       0.0, p_false=p, sigma_m=0.01)  # fmt: skip


def test_training_set_groups_bursts_priors_and_the_swept_volume():
    policy = TrainingPolicy(body_radius_m=0.2, body_half_height_m=0.05, free_voxel_m=0.1)
    o = [
        obs(0, 0.0, [0, 0, 1], 0, 0, 0.2), obs(1, 0.0, [-0.1, 0, 1], -1, 0, 0.2),
        obs(2, 1.0, [0, 0.1, 1], 0, 1), obs(3, 1.0, [-0.1, 0.1, 1], -1, 1),
        obs(4, 20.0, [0, 3, 1], 0, 2, 0.9), obs(5, 20.0, [-0.1, 3, 1], -1, 2, 0.9),
        # free space: the body (r 0.2) swept through event 2's contact at t = 10 s
        obs(6, 10.0, [0.05, 3.0, 1.0], 1, -1), obs(7, 10.01, [0.06, 3.0, 1.0], 1, -1),
        obs(8, 5.0, [1.0, 0.0, 1.0], 1, -1),
    ]  # fmt: skip
    ts = build_training_set(o, policy)
    assert len(ts) == 8  # two free points share a 0.1 m voxel
    assert list(ts.groups.prior_false) == [0.2, policy.prior_false, 0.9]
    b = ts.groups.burst
    assert b[0] == b[1] != b[2]  # 1 s and 0.1 m apart: one burst; event 2 far off
    assert list(ts.swept) == [False, False, True]
    assert ts.groups.extra_llr[2] == policy.sweep_llr


@pytest.mark.parametrize("disc", [0.0, 0.1])
def test_the_body_passing_through_a_contacts_tangent_disc_refutes_it(disc):
    """A touch on a wall x = 0 (normal +x). Later the body flies along the wall touching it
    (event 0's side: no refutation), and through the wall's plane 0.25 m beside event 1's
    contact: outside the body's reach of the point (0.17 m) but within it of the disc (0.1 m
    round the contact), so only the disc test refutes it."""
    policy = TrainingPolicy(body_radius_m=0.2, body_half_height_m=0.05, sweep_disc_m=disc)
    x = np.array([1.0, 0.0, 0.0])

    def touch(i, t, c, e):
        c = np.asarray(c, float)
        return [
            Observation(i, int(t * 1e9), c, 0.0, x, e, 0.0, p_false=0.1, sigma_m=0.01),
            Observation(i + 1, int(t * 1e9), c - 0.1 * x, -1.0, x, e, 0.0, p_false=0.1,
                        sigma_m=0.01),
        ]  # fmt: skip

    o = touch(0, 0.0, [0, 0, 1], 0) + touch(2, 30.0, [0, 3, 1], 1)
    o += [obs(4, 10.0, [0.21, 0.1, 1.0], 1, -1), obs(5, 40.0, [0.0, 3.25, 1.0], 1, -1)]
    ts = build_training_set(o, policy)
    assert list(ts.swept) == [False, disc > 0]
    assert ts.groups.extra_llr[1] == (policy.sweep_llr if disc > 0 else 0.0)


@pytest.mark.parametrize(
    ("underside", "other_x"), [(None, 0.0), (0.05, -0.15), (0.9, -0.15), (0.05, 0.15)]
)
def test_a_disc_reaching_past_an_edge_the_other_face_shows_is_no_refutation(underside, other_x):
    """A deck (x < 0, 1.0 <= z <= 1.3): its end face x = 0 (normal +x) touched 0.06 m above
    its lower edge; the tangent disc (0.1 m) reaches 0.04 m below the deck, where the vehicle
    later flies (centre 0.1 m under the deck's end, at z = 0.96). A touch of the underside
    (normal -z, at ``other_x``) that the detector vouches for shows the end face stops at
    z = 1: the rim points below it are no probes, and the touch stands. Without that touch,
    with one the detector doubts (prior above ``plane_max_p_false``), or with a downward-facing
    touch in front of the end face (x = +0.15: no face of the same solid; a gust in front of
    a touched wall is no edge of it) the disc refutes it as before."""
    policy = TrainingPolicy(body_radius_m=0.2, body_half_height_m=0.05, sweep_disc_m=0.1,
                            plane_max_p_false=0.3)  # fmt: skip

    def touch(i, t, c, n, e, p):
        c, n = np.asarray(c, float), np.asarray(n, float)
        return [
            Observation(i, int(t * 1e9), c, 0.0, n, e, 0.0, p_false=p, sigma_m=0.01),
            Observation(i + 1, int(t * 1e9), c - 0.1 * n, -1.0, n, e, 0.0, p_false=p,
                        sigma_m=0.01),
        ]  # fmt: skip

    o = touch(0, 0.0, [0.0, 0.0, 1.06], [1, 0, 0], 0, 0.05)
    if underside is not None:
        o += touch(2, 5.0, [other_x, 0.0, 1.0], [0, 0, -1], 1, underside)
    o += [obs(4, 20.0, [-0.1, 0.0, 0.96], 1, -1)]
    ts = build_training_set(o, policy)
    assert bool(ts.swept[0]) == (underside != 0.05 or other_x > 0)
    assert not np.any(ts.swept[1:])  # the underside's own disc lies above the vehicle


@pytest.mark.parametrize(
    ("half_h", "along", "normal", "placed_m", "refuted"),
    [
        (0.025, True, "top", 0.022, False), (0.025, True, "top", 0.045, False),
        (0.025, True, "side", 0.0, True), (0.025, False, "side", 0.0, False),
        (0.05, True, "top", 0.022, False), (0.05, True, "top", 0.035, True),
        (0.05, False, "side", 0.0, False), (0.05, False, "top", 0.04, True),
        (0.05, True, "none", 0.04, True),
    ],
)  # fmt: skip
def test_a_contact_is_refuted_only_beyond_its_tolerance(half_h, along, normal, placed_m, refuted):
    """A body of half-height ``half_h`` (tolerance 0.03 m) later *rests* on a deck top
    (z = 1.2, for 10 s), after a touch of that top placed ``placed_m`` high. With the
    tolerance along the normal (``along``: a guarded quadrotor, which touches with thin
    rings), the touch is refuted only if it lies inside the body wherever within the tolerance
    along its normal it really was. A body 0.05 m thick is thinner than that band: no sample
    of it refutes a top touch (before, a body assumed 0.1 m thick and shrunk by the tolerance
    all round refuted top touches placed 1-2 cm high). A side touch (normal +x, 0.1 m inside
    the body's radius) 0.024 m below the resting centre is within the body's own half-height,
    which the tolerance along x leaves whole: refuted; with the tolerance all round (the
    cylinder, whose flat side wall may have touched anywhere on it) it is not, at either
    thickness. A body 0.1 m thick refutes a top touch placed 0.035 m high along the normal
    (beyond the tolerance) and 0.04 m high all round, not one placed 0.022 m high. A probe
    without a normal keeps the body shrunk all round."""
    policy = TrainingPolicy(body_radius_m=0.25, body_half_height_m=half_h, sweep_disc_m=0.0,
                            sweep_tolerance_m=0.03, tolerance_along_normal=along)  # fmt: skip
    n = np.asarray({"top": [0, 0, 1.0], "side": [1.0, 0, 0], "none": [0, 0, 0.0]}[normal])
    c = np.array([0.1, 0.0, 1.2 + placed_m]) if normal != "side" else np.array([0.1, 0, 1.201])
    c[2] += 0.0 if normal != "side" else half_h - 0.025
    inner = c - 0.1 * (n if n.any() else np.array([0, 0, 1.0]))
    o = [
        Observation(0, 0, c, 0.0, n, 0, 0.0, p_false=0.05, sigma_m=0.01),
        Observation(1, 0, inner, -1.0, n, 0, 0.0, p_false=0.05, sigma_m=0.01),
    ]
    o += [obs(2 + k, 20.0 + 2 * k, [0.0, 0.0, 1.2 + half_h], 1, -1) for k in range(5)]  # at rest
    ts = build_training_set(o, policy)
    assert bool(ts.swept[0]) == refuted


@pytest.mark.parametrize("window", [0.0, 0.5])
def test_the_vehicle_at_a_touch_is_its_companion(window):
    """A touch on the top of a box (z = 1, normal +z) by a body 0.05 m thick: the vehicle's
    centre 0.05 m above it, sampled just before the impulse, is the touch's companion (within
    ``companion_s``). Samples behind the contact's plane, beyond the body's reach, long
    before, or nearly as far in front as the +1 label's clearance (0.2 m) are not."""
    policy = TrainingPolicy(companion_s=window, free_voxel_m=0.01, body_radius_m=0.2,
                            body_half_height_m=0.05)  # fmt: skip
    z = np.array([0.0, 0.0, 1.0])
    c = np.array([0.0, 0.0, 1.0])
    o = [
        Observation(0, int(10e9), c, 0.0, z, 0, 0.0, p_false=0.05, sigma_m=0.01),
        Observation(1, int(10e9), c - 0.1 * z, -1.0, z, 0, 0.0, p_false=0.05, sigma_m=0.01),
        obs(2, 9.95, [0.02, 0.0, 1.05], 1, -1),  # the centre as the body met the top
        obs(3, 9.9, [0.0, 0.1, 0.98], 1, -1),  # behind the plane: evidence against the touch
        obs(4, 9.8, [0.3, 0.0, 1.05], 1, -1),  # beyond the body's reach
        obs(5, 2.0, [0.0, 0.05, 1.05], 1, -1),  # long before: not the body at this touch
        obs(6, 10.1, [0.0, -0.05, 1.18], 1, -1),  # 0.18 m up: as clear as +1 says (0.2 m)
    ]
    ts = build_training_set(o, policy)
    comp = ts.groups.companion
    if not window:
        assert comp is None
        return
    assert comp.tolist() == [0, -1, -1, -1, -1] + [-1] * (len(ts) - 5)
    assert ts.groups.row_group[:5].tolist() == [-1] * 5  # still free rows of the fit
    assert ts.y[:5].tolist() == [1.0] * 5


@pytest.mark.parametrize(
    ("normal", "sample", "crossed"),
    [
        ("side", [-0.05, 0.12, 1.0], True),  # 0.05 m in front of a wall touched on the side
        ("side", [-0.22, 0.05, 1.0], False),  # the centre where the body keeps it: 0.2 m
        ("side", [0.05, 0.05, 1.0], False),  # behind the plane: the GP's evidence, not this
        ("top", [0.05, 0.0, 1.05], False),  # the cylinder resting on the top: 0.05 m up
        ("top", [0.05, 0.0, 1.01], True),  # its centre 1 cm above the top: the body is in it
    ],
)
@pytest.mark.parametrize("on", [True, False])
def test_a_body_nearer_a_contacts_plane_than_it_can_be_crosses_the_event(
    normal, sample, crossed, on
):
    """A free-space sample 0.15 s after a touch (inside the time the swept test skips), within
    the body's reach of the contact: where the cylinder (r 0.2 m, 0.05 m half height) could not
    have its centre at a true touch, nearer the contact's plane than its own extent along the
    normal less the tolerance (0.17 m side, 0.02 m top), it is no companion and the event is
    crossed (``swept``, ``sweep_llr`` nats); elsewhere a sample in front within the clearance
    stays a companion (``mapping.body_clearance`` off: always, as before)."""
    policy = TrainingPolicy(companion_s=0.5, free_voxel_m=0.01, body_radius_m=0.2,
                            body_half_height_m=0.05, sweep_tolerance_m=0.03,
                            body_clearance=on)  # fmt: skip
    n = np.array([-1.0, 0.0, 0.0]) if normal == "side" else np.array([0.0, 0.0, 1.0])
    c = np.array([0.0, 0.0, 1.0])
    o = [
        Observation(0, int(10e9), c, 0.0, n, 0, 0.0, p_false=0.05, sigma_m=0.01),
        Observation(1, int(10e9), c - 0.1 * n, -1.0, n, 0, 0.0, p_false=0.05, sigma_m=0.01),
        obs(2, 10.15, sample, 1, -1),
    ]
    ts = build_training_set(o, policy)
    hit = crossed and on
    assert bool(ts.swept[0]) == hit
    assert ts.groups.extra_llr[0] == (policy.sweep_llr if hit else 0.0)
    ahead = float((np.asarray(sample) - c) @ n)
    assert ts.groups.companion[0] == (0 if 0 < ahead < 0.15 and not hit else -1)


@pytest.mark.parametrize(
    ("other_normal", "other_p_false", "crossed"),
    [
        ([-1.0, 0.0, 0.0], 0.02, False),  # a believed touch on the same face: the body tumbled
        ([-0.97, 0.0, 0.26], 0.02, False),  # ... its normal 15 degrees off: still that face
        ([-1.0, 0.0, 0.0], 0.8, True),  # a doubted event vouches for nothing
        ([0.0, -1.0, 0.0], 0.02, True),  # another face (a corner): no vouching
    ],
)
def test_a_believed_touch_on_the_same_plane_vouches_for_a_crossed_event(
    other_normal, other_p_false, crossed
):
    """The side touch of the test above, crossed by a sample 0.05 m in front of its plane, and
    a second event 0.06 m along the wall (within twice ``sweep_disc_m``): where that one is a
    touch the detector believes on the same plane, the wall is there and the body was not
    level; otherwise the crossing stands."""
    policy = TrainingPolicy(companion_s=0.5, free_voxel_m=0.01, body_radius_m=0.2,
                            body_half_height_m=0.05, sweep_tolerance_m=0.03,
                            body_clearance=True, plane_max_p_false=0.3,
                            sweep_disc_m=0.1)  # fmt: skip
    n = np.array([-1.0, 0.0, 0.0])
    m = np.asarray(other_normal)
    c, c2 = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.06, 1.0])
    o = [
        Observation(0, int(10e9), c, 0.0, n, 0, 0.0, p_false=0.05, sigma_m=0.01),
        Observation(1, int(10e9), c - 0.1 * n, -1.0, n, 0, 0.0, p_false=0.05, sigma_m=0.01),
        Observation(2, int(30e9), c2, 0.0, m, 1, 0.0, p_false=other_p_false, sigma_m=0.01),
        Observation(
            3, int(30e9), c2 - 0.1 * m, -1.0, m, 1, 0.0, p_false=other_p_false, sigma_m=0.01
        ),  # fmt: skip
        obs(4, 10.15, [-0.05, -0.12, 1.0], 1, -1),
    ]
    ts = build_training_set(o, policy)
    assert bool(ts.swept[0]) == crossed


def test_the_body_extent_is_the_least_support_within_the_normal_error():
    """``_body_extent`` against a dense sampling of the directions within
    ``NORMAL_ERROR_DEG`` of each normal: the least support distance of the level inner
    cylinder over them, less the tolerance."""
    from groundstation.mapping.training import NORMAL_ERROR_DEG, _body_extent

    rng = np.random.default_rng(3)
    policy = TrainingPolicy(body_radius_m=0.18, body_half_height_m=0.025, sweep_tolerance_m=0.03)
    normals = rng.normal(size=(40, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[0] = [0.0, 0.0, 1.0]
    got = _body_extent(normals, policy)
    cone = math.cos(math.radians(NORMAL_ERROR_DEG))
    v = rng.normal(size=(200_000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for k, n in enumerate(normals):
        w = v[v @ n >= cone]
        support = 0.18 * np.hypot(w[:, 0], w[:, 1]) + 0.025 * np.abs(w[:, 2])
        assert got[k] == pytest.approx(support.min() - 0.03, abs=2e-3)
    assert got[0] == pytest.approx(0.025 - 0.03)  # straight up: the half height
    assert _body_extent(np.zeros((1, 3)), policy)[0] == -np.inf  # no normal: no extent


def test_a_burst_is_evidence_against_its_events_unless_the_detector_vouches_for_them():
    """Three events 1 s and 0.1 m apart form a burst: ``burst_llr`` for 'false' on each whose
    prior is at least ``burst_min_p_false`` (a gust cluster, or events of unknown origin), none
    on impacts the detector is sure of (a pilot tapping a spot)."""
    policy = TrainingPolicy()

    def taps(p_false):
        o = []
        for k in range(3):
            p = [0.0, 0.05 * k, 1.0]
            q = [-0.1, 0.05 * k, 1.0]
            o += [
                obs(2 * k, float(k), p, 0, k, p_false[k]),
                obs(2 * k + 1, float(k), q, -1, k, p_false[k]),
            ]
        return build_training_set(o, policy).groups

    g = taps([0.6, 0.01, math.nan])  # a gust, a vouched-for impact, an event without p_false
    assert len(set(g.burst.tolist())) == 1
    assert list(g.extra_llr) == [policy.burst_llr, 0.0, policy.burst_llr]
    assert list(taps([0.01, 0.02, 0.008]).extra_llr) == [0.0, 0.0, 0.0]


def test_rows_come_in_order_one_per_group_voxel_and_loose_contacts_group_into_runs():
    """Free rows first (the first sample of each free voxel, by id), then each group's
    voxels (groups in the order of their first observation, one row per voxel and label at
    its samples' mean); contacts without an event form runs split by ``event_gap_s``."""
    policy = TrainingPolicy(contact_voxel_m=0.05, free_voxel_m=0.1, event_gap_s=0.2)
    o = [
        obs(9, 0.3, [0.0, 0.51, 1.0], 0, -1), obs(3, 0.0, [0.0, 0.21, 1.0], 0, 7),
        obs(4, 0.0, [0.0, 0.22, 1.0], 0, 7), obs(5, 0.0, [-0.1, 0.21, 1.0], -1, 7),
        obs(8, 0.2, [0.0, 0.50, 1.0], 0, -1), obs(10, 0.9, [0.0, 0.80, 1.0], 0, -1),
        obs(1, 5.0, [1.0, 0.0, 1.0], 1, -1), obs(2, 5.1, [1.03, 0.0, 1.0], 1, -1),
        obs(6, 6.0, [2.0, 0.0, 1.0], 1, -1),
    ]  # fmt: skip
    ts = build_training_set(o, policy)
    assert [m.tolist() for m in ts.row_members] == [[1], [6], [3, 4], [5], [8, 9], [10]]
    assert list(ts.groups.row_group) == [-1, -1, 0, 0, 1, 2]
    np.testing.assert_allclose(ts.X[2], [0.0, 0.215, 1.0])
    assert list(ts.y) == [1.0, 1.0, 0.0, policy.inside_value, 0.0, 0.0]
    assert list(ts.event_ids) == [7, -1, -1]  # 8 and 9 0.1 s apart: one run; 10 0.6 s later
    assert ts.keys == (("e", 7), ("o", 8), ("o", 10))
    assert [g.tolist() for g in ts.group_ids] == [[3, 4, 5], [8, 9], [10]]
    assert list(ts.t_end_ns) == [0, int(0.3e9), int(0.9e9)]


def test_settled_events_are_pooled_with_their_summed_precision():
    """Two settled events in one 0.1 m voxel become one trusted row (per label) at their
    precision-weighted mean with the summed precision; an unsettled one keeps its group."""
    policy = TrainingPolicy(settled_voxel_m=0.1, contact_voxel_m=0.05)
    o = [
        obs(0, 0.0, [0.0, 0.01, 1.01], 0, 0), obs(1, 0.0, [-0.1, 0.01, 1.01], -1, 0),
        obs(2, 9.0, [0.0, 0.07, 1.03], 0, 1), obs(3, 9.0, [-0.1, 0.07, 1.03], -1, 1),
        obs(4, 20.0, [0.0, 0.05, 1.02], 0, 2), obs(5, 20.0, [-0.1, 0.05, 1.02], -1, 2),
        obs(6, 5.0, [1.0, 0.0, 1.0], 1, -1),
    ]  # fmt: skip
    plain = build_training_set(o, policy)
    keys = frozenset(plain.keys[:2])
    ts = build_training_set(o, policy, keys)
    assert list(ts.settled) == [True, True, False] and ts.keys == plain.keys
    rg = ts.groups.row_group
    assert np.sum(rg == 2) == np.sum(plain.groups.row_group == 2) == 2
    for label in (0.0, policy.inside_value):
        old = (plain.y == label) & np.isin(plain.groups.row_group, [0, 1])
        new = (ts.y == label) & (rg == -1)
        assert new.sum() == 1
        w_old = 1.0 / plain.noise_var[old]
        assert 1.0 / ts.noise_var[new][0] == pytest.approx(w_old.sum())
        np.testing.assert_allclose(ts.X[new][0], w_old @ plain.X[old] / w_old.sum())
        assert set(ts.row_members[int(np.flatnonzero(new)[0])].tolist()) == set(
            np.concatenate([plain.row_members[k] for k in np.flatnonzero(old)]).tolist()
        )
    assert [g.tolist() for g in ts.group_ids] == [g.tolist() for g in plain.group_ids]


def test_plane_points_of_many_touches_are_judged_as_each_alone():
    """``_plane_keep`` judges every group's plane points at once; each group's answer is the
    one it gets alone (random touches on the faces of a box and a pillar, some normals
    unknown, some centroids missing)."""
    rng = np.random.default_rng(3)
    for _ in range(40):
        G = int(rng.integers(2, 40))
        cen = rng.uniform(0.0, 0.8, (G, 3))
        nrm = np.eye(3)[rng.integers(0, 3, G)] * rng.choice([-1.0, 1.0], (G, 1))
        tilted = rng.random(G) < 0.4
        nrm[tilted] = rng.normal(size=(int(tilted.sum()), 3))
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        nrm[rng.random(G) < 0.1] = 0.0
        cen[rng.random(G) < 0.05] = np.nan
        groups = np.flatnonzero(nrm.any(axis=1) & np.isfinite(cen).all(axis=1))
        a = np.cross(nrm[groups], [0.0, 0.0, 1.0])
        a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
        b = np.cross(nrm[groups], a)
        tangents = np.stack([a, -a, b, -b], axis=1)
        reach = float(rng.choice([0.1, 0.2]))
        guard, solid = rng.choice([0.0, 0.3, 0.8], 2).tolist()
        together = _plane_keep(groups, tangents, cen, nrm, reach, guard, solid)
        assert together.shape == (groups.size, 4)
        for i, g in enumerate(groups):
            alone = _plane_keep(
                groups[i : i + 1], tangents[i : i + 1], cen, nrm, reach, guard, solid
            )
            assert np.array_equal(alone[0], together[i]), g
    none = _plane_keep(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 3)), cen, nrm, 0.2, 0.5, 0.5)
    assert none.shape == (0, 4)


def test_an_event_no_other_events_contact_comes_near_is_uncorroborated():
    """Uncorroborated: no other event's contact within ``lone_reach_m`` of the event's own
    centroid, counting only the events that vouch (a settled neighbour corroborates as any;
    one the map believes false does not)."""
    n = np.array([-1.0, 0.0, 0.0])

    def touch(i, t, y):
        at = np.array([0.0, y, 1.0])
        return [
            Observation(2 * i, int(t * 1e9), at, 0.0, n, i, 0.0, sigma_m=0.01),
            Observation(2 * i + 1, int(t * 1e9), at - 0.1 * n, -1.0, n, i, 0.0, sigma_m=0.01),
        ]

    obs = touch(0, 0.0, 0.0) + touch(1, 5.0, 0.4) + touch(2, 10.0, 2.0)
    ts = build_training_set(obs, TrainingPolicy(lone_reach_m=0.5))
    assert ts.uncorroborated().tolist() == [False, False, True]
    assert [c.tolist() for c in ts.corroborators] == [[1], [0], []]
    # the first believed false: the second has no one left to vouch for it
    assert ts.uncorroborated(np.array([False, True, True])).tolist() == [False, True, True]
    assert ts.uncorroborated(np.zeros(3, dtype=bool)).tolist() == [True] * 3
    near = build_training_set(obs, TrainingPolicy(lone_reach_m=0.3))
    assert near.uncorroborated().tolist() == [True] * 3
    settled = frozenset({ts.keys[0]})
    assert build_training_set(
        obs, TrainingPolicy(lone_reach_m=0.5), settled
    ).uncorroborated().tolist() == [False, False, True]
    off = build_training_set(obs, TrainingPolicy(lone_reach_m=0.0))
    assert off.uncorroborated(np.zeros(3, dtype=bool)).tolist() == [False] * 3


def test_a_lone_touch_goes_on_as_plane_points_and_a_crowded_one_does_not():
    """A touch with no other event's contact within ``plane_reach_m`` adds four contact rows
    that far along its tangents (in its own group, so its fate is theirs); two touches closer
    than that speak for the surface between them and add none; and no plane point is added
    where another touch's face says there is no surface, or round a bend two touches show, or
    for a touch the detector doubts."""
    policy = TrainingPolicy(tangent_slope_noise=1.0, plane_reach_m=0.2, plane_noise_per_m=0.5)
    n = np.array([-1.0, 0.0, 0.0])

    def touch(i, t, y, event, x=0.0, normal=n):
        at = np.array([x, y, 1.0])
        return [
            Observation(2 * i, int(t * 1e9), at, 0.0, normal, event, 0.0, sigma_m=0.01),
            Observation(2 * i + 1, int(t * 1e9), at - 0.1 * normal, -1.0, normal, event, 0.0,
                        sigma_m=0.01),
        ]  # fmt: skip

    def planes(ts):
        value = np.einsum("ij,ij->i", ts.directions, ts.directions) == 0.0
        return value & (ts.y == 0.0) & np.array([len(m) == 0 for m in ts.row_members])

    lone = build_training_set(touch(0, 0.0, 0.0, 0) + touch(1, 5.0, 1.0, 1), policy)
    p = planes(lone)
    assert p.sum() == 8  # four per touch
    assert set(lone.groups.row_group[p].tolist()) == {0, 1}
    np.testing.assert_allclose(lone.X[p][:, 0], 0.0)  # in the touched plane x = 0 ...
    d = np.linalg.norm(lone.X[p] - np.array([0.0, 0.0, 1.0]), axis=1)
    np.testing.assert_allclose(np.sort(d)[:4], 0.2)  # ... 0.2 m from their touch
    np.testing.assert_allclose(lone.noise_var[p], policy.contact_noise**2 + (0.5 * 0.2) ** 2)
    crowded = build_training_set(touch(0, 0.0, 0.0, 0) + touch(1, 5.0, 0.15, 1), policy)
    assert planes(crowded).sum() == 0
    assert not lone.uncorroborated().any() and not crowded.uncorroborated().any()  # reach 0: none
    off = build_training_set(touch(0, 0.0, 0.0, 0), dataclasses.replace(policy, plane_reach_m=0.0))
    assert planes(off).sum() == 0
    # a touch the detector doubts (p_false above plane_max_p_false) carries no surface on
    doubted = [dataclasses.replace(o, p_false=0.5) for o in touch(0, 0.0, 0.0, 0)]
    gated = dataclasses.replace(policy, plane_max_p_false=0.3)
    assert planes(build_training_set(doubted, gated)).sum() == 0
    assert planes(build_training_set(touch(0, 0.0, 0.0, 0), gated)).sum() == 4  # prior 0.1
    # a box corner: touch 0 on the face x = 0, 0.1 m from the edge y = 0, whose other face
    # touch 1 touched; touch 0's plane stops at that face (its point at y = -0.1 lies outside
    # it), touch 1's keeps all four (its point nearest the corner, x = 0.1, is still inside)
    side = np.array([0.0, -1.0, 0.0])
    corner = build_training_set(touch(0, 0.0, 0.1, 0) + touch(1, 5.0, 0.0, 1, 0.3, side), policy)
    p = planes(corner)
    rg = corner.groups.row_group[p]
    assert (rg == 0).sum() == 3 and (rg == 1).sum() == 4
    assert corner.X[p][rg == 0][:, 1].min() == pytest.approx(0.1)  # nothing past y = 0
    # a pillar of radius 0.3 m round the z axis touched at two sides 90 deg apart: each
    # touch's plane stops short of the way the surface bends towards the other (that point
    # would lie 7.6 cm off the pillar) and goes on along the axis and away from it
    pillar = build_training_set(
        touch(0, 0.0, 0.0, 0, -0.3) + touch(1, 5.0, -0.3, 1, 0.0, side), policy
    )
    p = planes(pillar)
    rg = pillar.groups.row_group[p]
    assert (rg == 0).sum() == 3 and (rg == 1).sum() == 3
    assert pillar.X[p][rg == 0][:, 1].min() == pytest.approx(0.0)  # none at y = -0.2 ...
    assert pillar.X[p][rg == 1][:, 0].min() == pytest.approx(0.0)  # ... nor at x = -0.2


def test_a_plane_point_stops_where_a_touch_within_the_guards_says_the_surface_ends():
    """``mapping.plane_guard_m`` and ``plane_guard_solid_m``: a wall touched 0.1 m above its
    lower edge, whose underside (a face of the same solid) was touched 0.68 m from the wall's
    lower plane point, loses that point once the solid's guard reaches so far. A box top 0.6 m
    in front of the wall is no face of the wall's solid: it cuts the wall's points off only
    within ``plane_guard_m`` (any touch), as the wall cuts the box's."""

    def touch(i, at, normal):
        at, normal = np.asarray(at, dtype=float), np.asarray(normal, dtype=float)
        return [
            Observation(2 * i, int(5e9 * i), at, 0.0, normal, i, 0.0, sigma_m=0.01),
            Observation(2 * i + 1, int(5e9 * i), at - 0.1 * normal, -1.0, normal, i, 0.0,
                        sigma_m=0.01),
        ]  # fmt: skip

    wall = touch(0, [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0])  # solid at x > 0
    under = touch(1, [0.3, 0.6, 0.9], [0.0, 0.0, -1.0])  # its underside, z = 0.9
    box = touch(2, [-0.6, 0.0, 0.9], [0.0, 0.0, 1.0])  # a box top in front of it, z = 0.9

    def plane_points(guard, solid):
        policy = TrainingPolicy(
            tangent_slope_noise=1.0, plane_reach_m=0.2, plane_guard_m=guard,
            plane_guard_solid_m=solid,
        )  # fmt: skip
        ts = build_training_set(wall + under + box, policy)
        value = np.einsum("ij,ij->i", ts.directions, ts.directions) == 0.0
        p = value & (ts.y == 0.0) & np.array([len(m) == 0 for m in ts.row_members])
        return [ts.X[p][ts.groups.row_group[p] == g] for g in range(3)]

    # both 0.5 m: the wall's four points lie 0.64-0.68 m from the others; the box's point
    # 0.4 m in front of the wall lies outside the wall's surface, within reach
    short = plane_points(0.5, 0.5)
    assert [len(x) for x in short] == [4, 4, 3]
    assert short[2][:, 0].max() == pytest.approx(-0.6)
    # the solid's guard at 1 m: the wall stops at its underside, the box's top cuts nothing
    solid = plane_points(0.5, 1.0)
    assert [len(x) for x in solid] == [3, 4, 3]
    assert solid[0][:, 2].min() == pytest.approx(1.0)  # nothing below the underside ...
    assert solid[0][:, 2].max() == pytest.approx(1.2)  # ... the point above the box stays
    # any touch's guard at 0.8 m: the box top cuts off the wall's points above z = 0.92 as
    # well, and the wall all but the box's farthest
    wide = plane_points(0.8, 0.8)
    assert [len(x) for x in wide] == [0, 4, 1]
    off = plane_points(0.0, 0.0)
    assert [len(x) for x in off] == [4, 4, 4]


def test_an_internal_row_another_face_of_the_solid_places_outside_it_is_left_out():
    """``mapping.internal_guard_m``: a box whose top is z = 1 and side x = 0 (solid at x > 0,
    z < 1). A side touch 1 cm below the top edge with its normal tilted 30 deg down across it
    puts its internal row 0.1 m back along that normal, 4 cm above the top: the top's touch
    says that is open space, so the row goes. A level side touch's row stays, and so does
    every row without the guard, or where the 'top' is a believed gust in front of the side
    (no face of its solid), or a touch the detector doubts."""
    tilt = np.array([-math.cos(math.radians(30)), 0.0, -math.sin(math.radians(30))])

    def touch(i, at, normal, p_false=0.0):
        at, normal = np.asarray(at, dtype=float), np.asarray(normal, dtype=float)
        return [
            Observation(2 * i, int(5e9 * i), at, 0.0, normal, i, p_false, sigma_m=0.01),
            Observation(2 * i + 1, int(5e9 * i), at - 0.1 * normal, -1.0, normal, i, p_false,
                        sigma_m=0.01),
        ]  # fmt: skip

    side = touch(0, [0.0, 0.0, 0.99], tilt)
    level = touch(1, [0.0, 1.0, 0.9], [-1.0, 0.0, 0.0])
    top = touch(2, [0.3, 0.2, 1.0], [0.0, 0.0, 1.0])

    def internal(obs, guard=0.5, plane_max_p_false=0.3):
        policy = TrainingPolicy(internal_guard_m=guard, plane_max_p_false=plane_max_p_false)
        ts = build_training_set(obs, policy)
        inner = ts.y < 0
        return sorted(ts.groups.row_group[inner].tolist()), ts

    groups_kept, ts = internal(side + level + top)
    assert groups_kept == [1, 2]  # the tilted side touch's row is gone; the others stay
    assert ts.X[(ts.y == 0.0) & (ts.groups.row_group == 0)].shape[0] == 1  # its contact stays
    assert internal(side + level + top, guard=0.0)[0] == [0, 1, 2]
    assert internal(side + level + top, guard=0.1)[0] == [0, 1, 2]  # the top is 0.3 m off
    doubted = [dataclasses.replace(o, p_false=0.5) for o in top]
    assert internal(side + level + doubted)[0] == [0, 1, 2]
    # the same 'top' touch 0.3 m in front of the side (x < 0): open space, no face of the box
    gust = touch(2, [-0.3, 0.2, 1.0], [0.0, 0.0, 1.0])
    assert internal(side + level + gust)[0] == [0, 1, 2]


def test_a_corner_whose_normal_is_tilted_is_one_solid_within_the_tilt_allowed():
    """``mapping.internal_guard_tilt_deg``: a box at x < 0.5, y < 0 (a MuJoCo dock flight,
    seed 132). The +y face's touch at x = 0.08 has its normal tilted 8 deg towards +x, which
    puts the +x face's touch at the corner 6 cm in front of its plane: not one solid at 2 cm,
    so the +x touch's internal row, tilted 14 deg across the corner and 3 cm in front of the
    +y face, stays. Allowing 15 deg (2 cm + 0.42 m sin 15 deg = 13 cm) it is one solid and the
    row goes. Two boxes' faces facing each other 1 m apart stay two solids at 20 deg."""
    from groundstation.mapping.training import one_solid

    def unit(v):
        v = np.asarray(v, dtype=float)
        return v / np.linalg.norm(v)

    def touch(i, at, normal, inner):
        at, normal = np.asarray(at, dtype=float), unit(normal)
        return [
            Observation(2 * i, int(5e9 * i), at, 0.0, normal, i, 0.1, sigma_m=0.01),
            Observation(2 * i + 1, int(5e9 * i), np.asarray(inner, dtype=float), -1.0, normal,
                        i, 0.1, sigma_m=0.01),
        ]  # fmt: skip

    n_side = unit([math.sin(math.radians(8)), math.cos(math.radians(8)), 0.0])
    side = touch(0, [0.08, 0.003, 1.5], n_side, [0.08, 0.003, 1.5] - 0.1 * n_side)
    n_end = unit([math.cos(math.radians(14)), -math.sin(math.radians(14)), 0.0])
    end = touch(1, [0.505, 0.01, 1.52], n_end, [0.505, 0.01, 1.52] - 0.1 * n_end)
    assert (end[1].position[1]) > 0.02  # the end touch's internal row is in front of the +y face

    def internal(tilt):
        policy = TrainingPolicy(
            internal_guard_m=0.5, plane_max_p_false=0.3, internal_guard_tilt_deg=tilt
        )
        ts = build_training_set(side + end, policy)
        return sorted(ts.groups.row_group[ts.y < 0].tolist())

    assert internal(0.0) == [0, 1]
    assert internal(15.0) == [0]
    a, b = np.array([[0.08, 0.003, 1.5]]), np.array([[0.505, 0.01, 1.52]])
    assert not one_solid(a, n_side[None], b, n_end[None])[0]
    assert one_solid(a, n_side[None], b, n_end[None], 15.0)[0]
    facing = (np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    far = (np.array([[1.0, 0.2, 1.0]]), np.array([[-1.0, 0.0, 0.0]]))
    assert not one_solid(facing[0], facing[1], far[0], far[1], 20.0)[0]


def test_the_internal_guards_tilt_is_checked():
    from groundstation.mapping.settings import MappingSettings

    for bad in (-1.0, 90.0, math.nan):
        with pytest.raises(ValueError, match="internal_guard_tilt_deg"):
            MappingSettings(internal_guard_tilt_deg=bad)
    assert MappingSettings(internal_guard_tilt_deg=15.0).internal_guard_tilt_deg == 15.0


def wavy_wall(seed=0, n=250):
    """Contacts on a wavy wall x = 0.08 sin(2 pi z / 0.7) over 3 m x 3 m, an internal point
    0.1 m behind each, free points in front: a surface whose length scale the data identify."""
    rng = np.random.default_rng(seed)
    yz = rng.uniform(0.0, 3.0, (n, 2))
    x = 0.08 * np.sin(2 * np.pi * yz[:, 1] / 0.7) + rng.normal(0.0, 0.005, n)
    wall = np.column_stack([x, yz])
    free = np.column_stack([rng.uniform(0.3, 0.8, n // 3), rng.uniform(0.0, 3.0, (n // 3, 2))])
    X = np.vstack([wall, wall - [0.1, 0.0, 0.0], free])
    y = np.concatenate([np.zeros(n), np.full(n, -0.5), np.ones(n // 3)])
    g = np.concatenate([np.arange(n), np.arange(n), np.full(n // 3, -1)])
    s2 = np.where(g < 0, 0.09, 0.0025)
    return X, y, s2, groups(g, 0.05)


def test_learn_theta_is_the_kernel_a_learning_fit_learns():
    X, y, s2, grp = wavy_wall(n=100)
    args = dict(lengthscale=0.3, signal_var=0.6, bounds=BOUNDS, max_iter=5)
    fitted = EventMixtureGPIS(**args).fit(X, y, s2, grp)
    theta = EventMixtureGPIS(**args).learn_theta(X, y, s2, grp)
    assert theta == (fitted.lengthscale_, fitted.signal_var_)
    assert theta != (0.3, 0.6)  # it was learnt, not handed back


def test_kernel_blocks_are_compact_even_and_cover_every_row_once():
    from groundstation.mapping.mixture import kernel_blocks

    rng = np.random.default_rng(0)
    X = rng.uniform(0.0, 1.0, (1000, 3)) * [4.0, 1.0, 1.0]  # a 4 m x 1 m x 1 m slab
    blocks = kernel_blocks(X, 300)
    assert sorted(np.concatenate(blocks).tolist()) == list(range(1000))
    assert all(125 <= b.size <= 300 for b in blocks) and len(blocks) == 4
    assert all(np.ptp(X[b, 0]) < 1.2 for b in blocks)  # cut across the long side
    assert [b.tolist() for b in kernel_blocks(X, 0)] == [list(range(1000))]
    assert [b.tolist() for b in kernel_blocks(X, 1000)] == [list(range(1000))]


def test_a_kernel_learnt_on_blocks_many_length_scales_wide_is_the_kernel_learnt_on_all():
    """The sum of the blocks' evidences drops only the correlations across their faces: on a
    3 m wall with 0.7 m waves, quarters learn the length scale within 10 % of the whole."""
    X, y, s2, grp = wavy_wall()
    args = dict(lengthscale=0.3, signal_var=0.6, bounds=KernelBounds((0.05, 2.0), (0.01, 5.0)))
    ell, sf2 = EventMixtureGPIS(**args).learn_theta(X, y, s2, grp)
    ell_b, sf2_b = EventMixtureGPIS(**args, kernel_block_rows=len(y) // 4 + 1).learn_theta(
        X, y, s2, grp
    )
    assert 0.1 < ell < 0.5  # identified, not at a bound
    assert ell_b == pytest.approx(ell, rel=0.1)
    assert sf2_b == pytest.approx(sf2, rel=0.15)


def test_contact_and_internal_rows_carry_their_mean_normal_pooled_or_not():
    policy = TrainingPolicy(settled_voxel_m=0.1, contact_voxel_m=0.05)
    n1, n2 = np.array([1.0, 0.0, 0.0]), np.array([0.8, 0.6, 0.0])

    def ob(i, x, label, event, n):
        return Observation(i, int(i * 1e9), np.asarray(x, float), float(label),
                           n if label <= 0 else np.zeros(3), event, 0.0, sigma_m=0.01)  # fmt: skip

    o = [ob(0, [0, 0.01, 1.01], 0, 0, n1), ob(1, [0, 0.02, 1.01], 0, 0, n2),
         ob(2, [0, 0.07, 1.03], 0, 1, n2), ob(3, [1.0, 0, 1], 1, -1, None)]  # fmt: skip
    plain = build_training_set(o, policy)
    contact = (plain.y == 0.0) & (plain.groups.row_group >= 0)
    np.testing.assert_allclose(plain.normals[contact], [(n1 + n2) / 2, n2])
    assert not plain.normals[plain.y > 0].any()  # free space has none
    value = np.einsum("ij,ij->i", plain.directions, plain.directions) == 0.0
    assert not plain.normals[~value].any()  # nor the tangent rows
    pooled = build_training_set(o, policy, frozenset(plain.keys))
    value = np.einsum("ij,ij->i", pooled.directions, pooled.directions) == 0.0
    row = (pooled.y == 0.0) & (pooled.groups.row_group == -1) & value
    np.testing.assert_allclose(pooled.normals[row], [((n1 + n2) / 2 + n2) / 2])
