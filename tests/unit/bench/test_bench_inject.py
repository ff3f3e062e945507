"""``bench inject``: the planted false contact (pure) and one real flight end to end."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.bench import detector as db
from groundstation.bench import inject
from groundstation.config import load_config
from groundstation.contact.detector import LABEL_INSIDE, LABEL_OUTSIDE, LABEL_SURFACE, Observation


def path(n=50):
    return [
        Observation(
            i,
            1_000_000_000 + i * 100_000_000,
            np.array([0.1 * i, 0.0, 1.0]),
            LABEL_OUTSIDE,
            np.zeros(3),
            -1,
            1.0,
        )  # fmt: skip
        for i in range(n)
    ]


def test_the_planted_contact_lies_on_the_rim_where_the_vehicle_flew():
    obs = path()
    p = inject.plant(obs, at=0.5, radius_m=0.2, internal_depth_m=0.1, seed=3)
    centre = next(o.position for o in obs if o.t_ns == p.t_ns)
    assert np.linalg.norm(p.contact - centre) == pytest.approx(0.2)
    assert p.contact[2] == pytest.approx(1.0)  # horizontal, at the vehicle's height
    labels = [o.label for o in p.observations]
    assert labels == [LABEL_SURFACE, LABEL_INSIDE] * 3
    assert {o.event_id for o in p.observations} == {inject.PLANTED_EVENT}
    ids = [o.id for o in p.observations]
    assert ids == list(range(50, 56))  # after every detector id
    inside = p.observations[1].position
    assert np.linalg.norm(inside - centre) == pytest.approx(0.3)  # behind the rim, away
    with pytest.raises(ValueError, match="no free-space"):
        inject.plant(obs[:0], at=0.5, radius_m=0.2, internal_depth_m=0.1)


def test_a_contact_planted_in_a_real_flight_is_refitted_and_weighed(external_data, tmp_path):
    log = db.import_real_flight(external_data, db.REAL_PATHS[0], db.REAL_FILES[0], tmp_path)
    row = inject.measure(str(log), "real", load_config(), at=0.5, seed=0)
    assert row["contacts_detected"] == 0  # a contact-free flight: the planted one is alone
    assert row["refits"] >= 1 and row["contact_refit_s"] is not None
    # the flight, which knows nothing of the planted 'structure', drifts on towards it within
    # the body's reach of the contact: nearer its plane than the body's centre can be at a
    # true touch (mapping.body_clearance), so the map decides it false outright
    assert row["flagged"] and row["p_false_map"] > 0.9
    # without that rule the flight never comes back through it and it carries no detector
    # p_false (prior 0.1), but the free space flown beside it speaks against it: its posterior
    # lies between the lone line (mapper.lone_flag_p, 0.2) and 1/2, so uncorroborated it is
    # decided false ...
    blind = ["mapping.body_clearance=false"]
    lone = inject.measure(str(log), "real", load_config(None, blind), at=0.5, seed=0)
    assert lone["flagged"] and 0.2 < lone["p_false_map"] < row["p_false_map"]
    assert lone["p_false_map"] < 0.5
    # ... and with one line for all (the rule before 673436c) it is kept at the same posterior
    one = inject.measure(str(log), "real", load_config(None, [*blind, "mapper.lone_flag_p=0.5"]),
                         at=0.5, seed=0)  # fmt: skip
    assert not one["flagged"] and one["p_false_map"] == pytest.approx(lone["p_false_map"])
    assert "**no**" in inject.markdown([one]) and "**no**" not in inject.markdown([row])
