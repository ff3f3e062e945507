"""Mapper core: data-clock schedule, skip-ahead, restore, duplicate ids, flag rule, failures.

Uses a tiny deterministic fake *model* only where the fit itself is not under test (the
schedule); the real SurfaceModel runs on a small synthetic sphere for the end-to-end checks.
"""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.contact.detector import Observation
from groundstation.errors import ConfigError, NotFittedError
from groundstation.mapping.mapper import (
    FLAG_AWAITING,
    FLAG_FALSE_POSITIVE,
    Mapper,
    MapperSettings,
    flag_observations,
)
from groundstation.mapping.surface import SurfaceMesh

S = 1_000_000_000


def obs(i, t_s, label, x=(0.0, 0.0, 0.0), event=-1):
    return Observation(i, int(t_s * S), np.asarray(x, float), float(label), np.zeros(3), event, 0.0)


class CountingModel:
    """Records every fit; u = 0.5 for contacts whose x > 10 (the 'false' ones), else 1e-6."""

    fits: list[int] = []

    def __init__(self, mapping, surface):
        self.fail = False

    def fit(self, X, y, ids, t_ns):
        if self.fail:
            raise NotFittedError("boom")
        CountingModel.fits.append(len(ids))
        self._ids, self._u = np.asarray(ids), np.where((X[:, 0] > 10) & (y == 0), 0.5, 1e-6)
        self.fit_ = self
        self.lengthscale_, self.converged_ = 0.3, True
        self.mode_, self.n_train_ = "exact", len(ids)
        return self

    def uncertainty_by_id(self):
        return self._ids, self._u

    def mesh(self):
        v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
        return SurfaceMesh(v, np.array([[0, 1, 2]]), np.zeros((3, 3)), np.zeros(3))


@pytest.fixture(autouse=True)
def _reset():
    CountingModel.fits = []


def make(**kw):
    return Mapper(MapperSettings(**kw), model_factory=CountingModel)


def test_schedule_follows_data_time_and_new_count():
    m = make(refit_period_s=2.0, refit_min_new=10, min_contacts=2)
    m.add([obs(0, 0.0, 1), obs(1, 0.5, 0, event=0)])
    assert not m.due()  # one contact only
    m.add([obs(2, 1.0, 0, event=0)])
    assert not m.due()  # 1 s of data since the first observation
    m.add([obs(3, 2.1, 1)])
    assert m.due()
    assert m.refit().fit_index == 0 and CountingModel.fits == [4]
    assert not m.due()  # nothing new
    m.add([obs(4, 3.0, 1)])
    assert not m.due(int(4.0 * S))  # 1.9 s after the last fit's data
    assert m.due(int(4.2 * S))
    m.refit()
    m.add([obs(10 + k, 4.2 + 0.01 * k, 1) for k in range(10)])  # 10 new in 0.1 s
    assert m.due()


def test_a_new_contact_with_its_internal_point_makes_a_refit_due_at_once():
    m = make(refit_period_s=2.0, refit_min_new=100, min_contacts=1)
    m.add([obs(0, 0.0, 1), obs(1, 0.1, 0, event=0), obs(2, 0.1, -1, event=0)])
    assert m.due()  # 0.1 s of data: the period alone would wait until 2.0 s
    m.refit()
    m.add([obs(3, 0.3, 1)])
    assert not m.due()  # free space alone waits for the period
    m.add([obs(4, 0.4, 0, event=1)])
    assert not m.due()  # the contact without its internal point: wait for the pair
    m.add([obs(5, 0.4, -1, event=1)])
    assert m.due()
    off = make(refit_period_s=2.0, refit_min_new=100, min_contacts=1, refit_on_contact=False)
    off.add([obs(0, 0.0, 1), obs(1, 0.1, 0, event=0), obs(2, 0.1, -1, event=0)])
    assert not off.due()


def test_refit_uses_everything_received_skip_ahead():
    m = make(refit_period_s=1.0, refit_min_new=1000)
    m.add([obs(0, 0, 1), obs(1, 0.1, 0, event=0), obs(2, 0.2, 0, event=0)])
    m.add([obs(3, 1.5, 1)])
    assert m.due()
    # the process fell behind: 50 more observations arrive before it gets to refit
    m.add([obs(100 + k, 2 + k * 0.1, 1) for k in range(50)])
    fit = m.refit()
    assert CountingModel.fits == [54] and len(fit.ids) == 54
    assert fit.data_ns == int((2 + 49 * 0.1) * S) == m.data_ns  # lag 0 right after the fit
    assert not m.due()


def test_duplicates_ignored_and_restore_rebuilds_everything():
    seen = [obs(0, 0, 1), obs(1, 0.1, 0, event=0), obs(2, 0.2, 0, event=1), obs(3, 3, 1)]
    m = make()
    assert m.add(seen) == 4 and m.add(seen[:2]) == 0 and m.duplicates == 2
    r = Mapper.restore(reversed(seen), MapperSettings(), model_factory=CountingModel)
    assert [o.id for o in r.observations()] == [0, 1, 2, 3]
    assert r.add(seen) == 0  # replay of the observation topic after restart: nothing twice
    assert r.due() and len(r.refit().ids) == 4


def test_flag_rule_flags_whole_event_and_only_contacts():
    s = MapperSettings(flag_u=0.1, flag_event_fraction=0.5)
    o = [
        obs(0, 1, 0, event=0), obs(1, 1, -1, event=0),  # event 0: suspect pair
        obs(2, 2, 0, event=0), obs(3, 2, -1, event=0),  # event 0: trusted pair
        obs(4, 3, 0, event=1), obs(5, 3, -1, event=1),  # event 1: trusted
        obs(6, 4, 1),  # external with a big u: never flagged
        obs(7, 5, 0, event=2), obs(8, 5, -1, event=2),
        obs(9, 6, 0, event=2), obs(10, 6, -1, event=2), obs(11, 7, 0, event=2),  # 1 of 3 suspect
    ]  # fmt: skip
    u = np.array([0.5, 9, 1e-6, 9, 1e-6, 1e-6, 5.0, 0.6, 1e-6, 1e-6, 1e-6, 1e-6])
    flags, events = flag_observations(o, u, s)
    assert events == (0,)
    assert flags.tolist() == [1, 1, 1, 1, 0, 0, 0, 1, 1, 0, 0, 0]  # event 0 whole; pair 7/8


def test_plateau_flags_nothing():
    """On the Gaussian plateau every u is alike and carries no per-datum information."""
    o = [obs(i, i, 0, event=i) for i in range(5)]
    u = np.array([0.9, 0.9, 0.95, 0.9, 0.9])
    flags, events = flag_observations(o, u, MapperSettings(flag_u=0.1), plateau=True)
    assert not flags.any() and events == ()


def test_flags_measure_u_above_the_noise_floor():
    """A high-noise fit (beta large) lifts every u: only the excess over beta/(alpha+1/2)
    counts, and a majority of false contacts is still flagged (no median rule)."""
    o = [obs(i, i, 0, event=i) for i in range(5)]
    u = np.array([0.45, 0.9, 0.92, 0.95, 0.91])  # event 0 fits exactly, four do not
    s = MapperSettings(flag_u=0.3)
    flags, events = flag_observations(o, u, s, u_floor=0.45)
    assert events == (1, 2, 3, 4) and flags.tolist() == [0, 1, 1, 1, 1]
    flags, events = flag_observations(o, u, s, u_floor=0.7)  # same u, higher floor
    assert events == () and not flags.any()


def test_failed_fit_keeps_last_good_mesh_and_flags():
    m = make(refit_min_new=1, min_contacts=1)
    m.add([obs(0, 0, 1), obs(1, 0.1, 0, (20, 0, 0), event=0), obs(2, 0.1, -1, event=0)])
    m.add([obs(4, 0.2, 0, event=1), obs(5, 0.3, 0, event=2)])  # trusted contacts
    good = m.refit()
    assert good.reliable and good.flags[1] & FLAG_FALSE_POSITIVE and good.mesh is not None
    m._model.fail = True  # noqa: SLF001 - the next fit raises
    m.settings = MapperSettings(refit_min_new=1, min_contacts=1, fallback=False)
    m.add([obs(3, 1, 1)])
    bad = m.refit()
    assert not bad.reliable and bad.reasons[0].startswith("fit_error")
    assert bad.mesh is good.mesh and bad.mesh_fit_index == good.fit_index
    assert bad.flags.tolist() == [0, 1, 1, 0, 0, 0] and bad.fit_index == 1


def test_fallback_replaces_a_failing_model():
    m = make(refit_min_new=1, min_contacts=1)
    m.add([obs(0, 0, 1), obs(1, 0.1, 0, event=0)])
    m.refit()
    m._model.fail = True  # noqa: SLF001
    m.add([obs(2, 1, 1)])
    fit = m.refit()  # fallback: a fresh model from the factory fits
    assert fit.reliable and fit.fallback == "gpis_init" and not m._model.fail  # noqa: SLF001


def test_real_model_on_a_sphere_flags_a_false_contact():
    rng = np.random.default_rng(0)
    o, i = [], 0
    for k in range(60):  # contacts + internal points on a sphere of radius 0.5 at (2, 2, 1)
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        c = np.array([2.0, 2.0, 1.0]) + 0.5 * n
        o += [obs(i, k * 0.1, 0, c, event=k), obs(i + 1, k * 0.1, -1, c - 0.1 * n, event=k)]
        i += 2
    for k in range(120):  # free space shell 0.8-1.2 m from the centre
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        o.append(obs(i, 6 + k * 0.05, 1, np.array([2.0, 2.0, 1.0]) + rng.uniform(0.8, 1.2) * n))
        i += 1
    o.append(obs(i, 20, 0, (2.0, 2.0, 1.95), event=99))  # a 'gust' contact in free space
    m = Mapper(MapperSettings(flag_u=0.05))
    m.add(o)
    fit = m.refit()
    assert fit.reliable and fit.mesh is not None and not fit.mesh.is_empty
    assert 99 in fit.flagged_events
    assert len(fit.flagged_events) <= 3  # the sphere's own contacts stay trusted


def test_settings_validated():
    with pytest.raises(ConfigError, match="refit_min_new"):
        MapperSettings(refit_min_new=0)
    with pytest.raises(ConfigError, match="flag_event_fraction"):
        MapperSettings(flag_event_fraction=1.5)


def _sphere_and_a_doubted_lone_touch():
    """The sphere above (touches the detector believes, free space round them), and far from
    it a lone touch the detector doubts (P(false) 0.45) that nothing refutes."""
    rng = np.random.default_rng(1)
    o, i = [], 0
    for k in range(60):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        c = np.array([2.0, 2.0, 1.0]) + 0.5 * n
        o += [
            Observation(i, int(k * 0.1 * S), c, 0.0, n, k, 2.0, p_false=0.01),
            Observation(i + 1, int(k * 0.1 * S), c - 0.1 * n, -1.0, n, k, 2.0, p_false=0.01),
        ]
        i += 2
    for k in range(120):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        o.append(obs(i, 6 + k * 0.05, 1, np.array([2.0, 2.0, 1.0]) + rng.uniform(0.8, 1.2) * n))
        i += 1
    lone = np.array([4.0, 4.0, 1.0])
    for k in range(2):
        c = lone + [0.02 * k, 0.0, 0.0]
        up = np.array([0.0, 0.0, 1.0])
        o += [
            Observation(i, int((10 + 0.04 * k) * S), c, 0.0, up, 77, 2.0, p_false=0.45),
            Observation(i + 1, int((10 + 0.04 * k) * S), c - 0.1 * up, -1.0, up, 77, 2.0,
                        p_false=0.45),
        ]  # fmt: skip
        i += 2
    return o, lone


@pytest.mark.parametrize("flag_p", [0.5, 0.25])
def test_flag_p_decides_the_map_and_the_flags_alike(flag_p):
    o, lone = _sphere_and_a_doubted_lone_touch()
    m = Mapper(MapperSettings(flag_p=flag_p, lone_flag_p=flag_p))
    m.add(o)
    fit = m.refit()
    assert fit.reliable and fit.mesh is not None and not fit.mesh.is_empty
    near = np.linalg.norm(fit.mesh.vertices - lone, axis=1).min()
    if flag_p < 0.45:
        assert fit.flagged_events == (77,)
        assert near > 1.0  # left out of the map: nothing is drawn round it
    else:
        assert 77 not in fit.flagged_events
        assert near < 0.15  # kept: the map draws it


def test_an_uncorroborated_doubted_touch_is_decided_on_the_lone_line_until_corroborated():
    """The lone touch the detector doubts (0.45) is flagged on the default lone line (0.2) and
    left out of the map; a later touch the detector believes, 0.3 m from it on the same face,
    corroborates it: both are then decided on ``flag_p`` and drawn."""
    o, lone = _sphere_and_a_doubted_lone_touch()
    m = Mapper(MapperSettings())
    m.add(o)
    fit = m.refit()
    assert fit.flagged_events == (77,) and fit.awaiting_events == (77,)
    assert np.linalg.norm(fit.mesh.vertices - lone, axis=1).min() > 1.0
    flags = fit.flags[np.isin(fit.ids, [o_.id for o_ in o if o_.event_id == 77])]
    assert np.all(flags == FLAG_FALSE_POSITIVE | FLAG_AWAITING)  # flagged, awaiting a 2nd touch
    up = np.array([0.0, 0.0, 1.0])
    i = max(o_.id for o_ in o) + 1
    c = lone + [0.3, 0.0, 0.0]
    m.add([
        Observation(i, int(20 * S), c, 0.0, up, 78, 2.0, p_false=0.01),
        Observation(i + 1, int(20 * S), c - 0.1 * up, -1.0, up, 78, 2.0, p_false=0.01),
    ])  # fmt: skip
    fit = m.refit()
    assert 77 not in fit.flagged_events and 78 not in fit.flagged_events
    assert fit.awaiting_events == () and not np.any(fit.flags & FLAG_AWAITING)
    assert np.linalg.norm(fit.mesh.vertices - lone, axis=1).min() < 0.15


def test_an_event_the_map_believes_false_corroborates_nothing():
    """A gust the detector is sure of (0.95), 0.3 m from the doubted lone touch, is flagged;
    it does not corroborate the touch, which stays on the lone line (flagged, not drawn). Two
    gusts of one cluster push the drone to the same place: one flagged must not keep the
    other on the line for corroborated events."""
    o, lone = _sphere_and_a_doubted_lone_touch()
    up = np.array([0.0, 0.0, 1.0])
    i = max(o_.id for o_ in o) + 1
    c = lone + [0.3, 0.0, 0.0]
    o += [
        Observation(i, int(12 * S), c, 0.0, up, 79, 2.0, p_false=0.95),
        Observation(i + 1, int(12 * S), c - 0.1 * up, -1.0, up, 79, 2.0, p_false=0.95),
    ]  # fmt: skip
    m = Mapper(MapperSettings())
    m.add(o)
    fit = m.refit()
    assert fit.flagged_events == (77, 79)
    assert fit.awaiting_events == (77,)  # the gust is flagged on its own posterior
    assert np.linalg.norm(fit.mesh.vertices - lone, axis=1).min() > 1.0
    # with every event vouching (the lone line as loose as flag_p), both lines are one
    m = Mapper(MapperSettings(lone_flag_p=0.5))
    m.add(o)
    assert m.refit().flagged_events == (79,)
