"""Settings of the mapping engine (frozen; defaults are the paper's unless a measurement says
otherwise, in which case the paper's value is named beside the default)."""

from __future__ import annotations

import dataclasses
from typing import Literal

from groundstation.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class MappingSettings:
    """How the implicit surface is estimated.

    Two engines (``engine``): ``mixture`` (default, ``mapping/model.py``) decides every contact
    event true or false with a posterior probability from its detector prior and the rest of the
    data (``mapping/mixture.py``); ``legacy`` is the previous per-datum Student-t pipeline
    (``mapping/legacy.py``: merge, exact/sparse robust GPIS, margin flags), kept for measured
    comparisons. Fields marked (legacy) only shape the legacy engine and the estimators
    ``GPIS``/``RobustGPIS`` the paper benches use.

    Attributes
    ----------
    engine : "mixture" | "legacy"
        Which mapping engine runs.
    lengthscale_max : float
        Upper bound of the learnt length scale, metres (mixture). With the floor
        ``lengthscale_min`` it ties the kernel to the map's resolution: the floor is twice the
        0.05 m grid, the cap seven times it. An uncapped fit on touch data smoothed boxes into
        blobs (l ~ 0.86 m: 25 % of the surface more than 0.1 m from the mesh). 0.35, not 0.5,
        since 2026-12-07: a kernel learnt at 0.395 m on 22 events of a crashed MuJoCo pier
        flight drew a 1.13 m² web under its deck (0.70 m² at 0.35 clipped, 0.11 m² held).
        With the hold off, judged against 0.5 by a rule written before the runs
        (docs/results-history.md, "cap-035"): mean largest patch 0.0323 -> 0.0307 m² on the
        tuning seeds 200-202 and 0.123 -> 0.120 m² on fresh seeds 122-124, every other figure
        within the rule (touches flagged 17 -> 17 of 808 and 16 -> 15 of 828).
    hold_at_cap : bool
        Off by default since the cap is 0.35 m: a smooth solid identifies a kernel above it (a
        sphere of radius 0.5 m, a pillar of 0.3 m: 0.39 m), and holding the configured 0.25 m
        there flagged 6 of the sphere's 60 touches and kept a gust above it; clipped to the cap
        the gust alone is flagged. On, with the old 0.5 m cap:
        a kernel step whose length scale ends at ``lengthscale_max`` is not taken (mixture):
        the evidence would have the field smoother still, which is what free space around a
        few touches asks for, not a surface that is smooth; the data do not identify the
        kernel, and the one in force (at first the configured one) holds until the rows grow
        by ``theta_refit_growth`` again (``kernel_held`` in the fit summary). Taken, the cap
        drew a crashed pier flight's deck as a 2.3 m² bulge and a free wall flight's wall as a
        0.6 m² one (reporting seeds 103 and 100, the only two flights of 153 whose final map
        sat at the cap). Tuning flights (seeds 200-202), where no final map sat at the cap:
        every map figure within noise (touches flagged 14 -> 13 of 810, Chamfer near touches
        40.1 -> 40.3 mm, phantom and missing unchanged), the controls identical.
    outlier_var : float
        Label variance of a false event's rows (mixture; the label scale is 1).
    contact_noise : float
        Label noise of a contact or internal row before its placement uncertainty (mixture).
    free_noise : float
        Label noise of a free-space row (mixture): a vehicle centre is outside by an unknown
        distance.
    free_voxel_m : float
        Free-space rows are thinned to one per voxel of this edge (mixture).
    prior_false : float
        Prior probability that a contact event is false when the detector gave no ``p_false``
        (mixture).
    burst_gap_s, burst_radius_m : float
        Events within ``burst_radius_m`` of a burst's first event, each at most ``burst_gap_s``
        after the previous one, form a burst, tested as one (mixture): about the vehicle's size,
        where a gust keeps pushing it while it holds position.
    burst_events_min, burst_llr : int, float
        A burst of at least ``burst_events_min`` events adds ``burst_llr`` nats of evidence that
        its events are false: real surface is touched on separate visits, a gust cluster in one
        window (``mapping/training.py``; 0 turns it off).
    burst_min_p_false : float
        ... but only to an event whose prior ``P(false)`` (the detector's ``p_false``, else
        ``prior_false``) is at least this: three impacts the detector vouches for, close in
        time and place, are a pilot tapping a spot, not a gust. On the tuning flights (seed
        200, contacts placed with ``contact.normal_spread_deg`` 20) no detected gust had
        ``p_false`` below 0.06 (117 gusts, 5 % below 0.29) and 62-77 % of the touches had it
        below 0.05. The bundled pillar survey taps the pillar's top three times in 5 s, 0.14 m
        apart (``p_false`` 0.007-0.009): with the burst evidence all three were flagged and 18 %
        of the surface near its touches went missing; without it none.
    sweep_llr : float
        Evidence (nats) that an event is false when its contact lies inside the vehicle's body at
        a free-space sample away from it: log(1 / 0.01), a true contact being there only through
        a placement error beyond ``sweep_tolerance_m`` (mixture).
    sweep_exclude_s, sweep_tolerance_m : float
        Free-space samples this close in time to the event do not count; a contact counts as
        inside the body only if it is wherever within the tolerance it really was: all round
        for the cylinder, along its normal for a guarded quadrotor (its placement error;
        ``mapping/training.py``; mixture).
    sweep_disc_m : float
        The swept-volume test covers each contact's tangent disc of this radius, not only the
        contact point (mixture; 0: the point alone). The surface a touch shows goes on round it,
        so the body cannot have passed there either. On the tuning flights (seeds 200-202,
        every detected event, 12 rim points) the body at a free-space sample away from the
        event cut the rim of 0.9 % of the 1,851 true touches and 65 % of the 359 gusts at
        0.1 m (the contacts' centroid alone: 0.5 % and 28 %; 0.15 m: 1.5 % and 67 %): a
        likelihood ratio of about e^4.3, near ``sweep_llr``'s e^4.6.
    companion_s : float
        A free-space sample taken within this time of a contact event, in front of its contact
        plane by less than three quarters of the clearance +1 stands for (0.15 m) and within
        the body's reach of it, is the event's *companion*: left out with the event when the
        mixture tests it, kept in the fit (mixture; ``mapping/training.py``; 0: none). It is
        the vehicle's centre at the contact, which the detector's geometry puts a body's extent
        in front of any contact it places, true or false: 0.05 m above the top of a box.
        Counted as evidence, its +1 that close to a 0 made the rest of the data doubt real
        touches on horizontal faces. Of the 32 touches and slow touches the final maps of the
        tuning flights flagged (seeds 200-202, gusty and control, both engines), 21 lay more
        than 0.1 m off any surface (right to flag), 2 the detector doubted, 3 the body later
        flew through, and 6 lay on the surface with only the GP's residual against them; the
        four checked (pillar and yard tops, simple physics) had the vehicle's centre sampled
        0.01-0.15 s before the impulse 5-10 cm above them. At 0.5 s without the 0.15 m limit
        (74a2599, where it was the default): tuning flights (36 gusty flights and their
        controls) touches flagged 15 -> 14 of 811 (controls 8 -> 6 of 762), gusts (360 of 372)
        and the largest phantom patch (0.124 m²) unchanged; reporting flights touches flagged
        27 -> 26 of 784, the rest unchanged. But on the paper-like 3D set (``bench pareto
        --scenes paper3d``) an isolated gust was kept, its sample 0.2 m in front of it (on the
        vehicle's side, as far as +1 says) having been what flagged it: largest phantom patch
        0.19 -> 0.53 m², Chamfer 27.5 -> 29.6 mm. With the limit, that set is as without
        companions and the two simple pillars' top touches are still cleared; with it (0.5 s,
        473f7ba) both flight sets gave the unlimited form's flags, flight for flight, and its
        surface figures within 1 mm and 0.005 m² (tuning: touches flagged 15 -> 14 of 811;
        reporting: 27 -> 26 of 784, missing within 0.2 m 0.068 -> 0.067 on the 39 gusty
        flights, nothing worse). Relabelling those samples to the clearance the body gives them
        (0.25 for 5 cm) instead cleared the same touches but let the field sag under the pier's
        deck (a control's patch 0.17 -> 0.36 m²): the +1 there is true free space.
    body_clearance : bool
        A free-space sample within ``companion_s`` of an event, within the body's reach of its
        contacts and in front of their plane by less than the body's own extent along the
        normal (its level inner cylinder's least support distance over the normals within 20
        degrees of the contact's, less ``sweep_tolerance_m``: 0.17 m for the cylinder's side
        touch, 0.02 m for its top touch) is no companion: the vehicle's body there reached past
        that plane beside the contact, which the body of a true touch cannot, and it refutes
        the event as the swept volume does (``sweep_llr``; the swept test itself skips the
        ``sweep_exclude_s`` round the event), unless a touch of another event that the
        detector believes shows the same plane next to it (``mapping/training.py``).
    mixture_max_iter : int
        Iterations of a cold mixture fit at most (warm refits: ``refit_max_iter``).
    learn_min_events : int
        The kernel is learnt only once the learning tile holds this many events the data trust
        (P(false) < 0.5); until then ``lengthscale`` and ``signal_var`` hold (mixture). Free
        space alone fits any length scale, best the cap, and one touch cannot pin it: a kernel
        learnt on it flagged that touch for being alone. On the tuning flights, 3 against 1:
        true touches flagged 5.9 % -> 1.4 % (flight mean), gusts flagged 99.4 % both. 10 against
        3 (2026-12-03, seeds 200-202): gusty flights over 0.1 m² of phantom 2 -> 4 of 31, mean
        largest patch 0.032 -> 0.039 m², missing by area 1.94 -> 2.02 %: waiting for more
        touches leaves the configured kernel in force on the flights with few of them
        (docs/results-history.md, "few-touches").
    learn_free_reach_m : float
        The kernel step sees only the free-space rows within this distance of a shape row
        (contact, internal or tangent) of its learning tile (mixture; 0: every free-space row).
        Free space far from every touch says only "no surface here", which the smoothest field
        fits best: with few touches amid a long path it pulls the length scale learnt towards
        the cap, and a map whose touches were cut short keeps that smooth kernel. The fits
        themselves keep every row. Off by default, as measured: far free space also holds the
        length scale up where the contacts are noisy. With 0.5 m on the tuning flights
        (``bench sessions --seeds 200-202``, gusty flights) the length scale fell by 10 % as a
        median over flights and by 30 % on MuJoCo's walls and yards (0.20 -> 0.13-0.14 m):
        flights over 0.1 m² of phantom 2 -> 2 of 31, mean largest patch 0.032 -> 0.033 m²,
        touched surface missing within 0.2 m 1.9 -> 2.4 % by area (MuJoCo 3.8 -> 4.7 %;
        controls 0.9 -> 1.8 %), touches flagged 17 -> 14 of 808, gusts flagged 309 -> 308 of
        309. On reporting seeds 116-118 (a development run after they were reported) it took
        the two largest patches away (with ``learn_min_events`` 10: 12 -> 10 of 32 over
        0.1 m², missing by area 3.6 -> 3.9 %). A trade of missing surface for phantom, not a
        gain: the option is kept so that these runs can be repeated.
    flag_inside : bool
        Whether a contact event that the rest of the data places *inside* the structure (its
        leave-out residual says the surface lies farther out than the model predicts) counts as
        evidence that it is false (mixture). A false contact's point lies where the vehicle
        flew, in free space, so only the rest of the data placing it outside refutes it; a
        contact the model predicts inside is a shape the kernel is too smooth for (a thin wall
        touched from both sides, a corner, a small sphere). Off (the default): such residuals
        add no evidence either way. On the tuning flights (``bench sessions --seeds 200``) off
        flagged 7 instead of 9 of 271 touches (controls 4 instead of 7 of 266) and the same 102
        of 104 gusts.
    flag_tol : float
        The mixture's EM stops when no event's posterior moves by more than this (or by more
        than ten times this while no decision flips).
    settle_p_false : float
        An event whose posterior P(false) is at most this at a refit, whose odds of being false
        the rest of the data lowered by ``settle_evidence_nats`` at least (corroborated, not
        just trusted by its prior), and that ended at least ``settle_after_s`` before the
        newest observation, is *settled* (mixture, live refits and ``--map final``'s fits):
        its fate is frozen as true and its contact and internal rows are pooled with every
        other settled event's per ``settled_voxel_m`` voxel (a pooled row carries the summed
        precision of the rows it replaces). Rows then grow with the touched area, not with the
        time spent sliding over it: on the dense sliding session (``bench pareto --scenes
        session40``) a revisited patch otherwise adds rows at every stroke. A settled event is
        re-tested only when the vehicle's body later passes through it (its swept volume); other
        later evidence no longer reaches it. 0: never settle.
    settle_after_s : float
        Age (after its last sample) at which a trusted event may settle, seconds of data time.
    settle_evidence_nats : float
        How much the data must have lowered an event's log odds of being false before it may
        settle. On the tuning flights an event with the detector's prior 0.008 and nothing
        near it settled at 60 s, and a later flag (the nosettle run) no longer reached it:
        its phantom patch grew from 0.29 to 1.19 m^2.
    settled_voxel_m : float
        Voxel edge of the settled pool, metres.
    tile_m : float
        Smallest edge of the cubic tiles the map is fitted in (mixture; ``mapping/tiles.py``):
        the edge is three length scales when that is longer; each tile is fitted on its rows plus
        a halo of three length scales, and only tiles whose data changed are refitted.
    learn_tile_m : float
        Edge of the tile the kernel is learnt on (the one holding the most trusted surface).
    kernel_block_rows : int
        A kernel step on more rows than this sums the evidence of spatial blocks of at most
        this many rows (``mixture.kernel_blocks``; 0: never). Each L-BFGS evaluation factorises
        its rows and inverts the factor, so its cost grows with their cube: on the dense
        40-minute session (sliding strokes, 0.1 m pooled voxels) the learning tile held up to
        4,700 rows and a kernel step took 10.6 s. The learning tiles of ordinary flights hold
        far fewer (at most ~600 on the tuning flights, 472 on the 40-minute survey, 1,043 on the
        paper-like 3D set): there the kernel step is unchanged.
    tangent_slope_noise : float
        Noise (label units per metre) of each event's two tangent-plane rows: the potential's
        derivative along the contact's tangents is 0, so a surface goes on flat around a touch
        instead of closing into a blob (mixture; 0: no tangent rows). On a potential rising
        about 5 per metre, 1.0 is a normal off by ~12 deg: the detector's event normals were
        measured 2.6 deg (median) off on the simple physics and 13.5 deg on MuJoCo (friction
        tilts the impulse). Tuning flights (seed 200) at 0.5 / 0.7 / 1.0 / 2.0, gusty means:
        missing within 0.5 m 0.305 / 0.304 / 0.308 / 0.329, Chamfer 0.068 / 0.067 / 0.067 /
        0.070 m, largest phantom patch 0.22 / 0.21 / 0.20 / 0.19 m², mesh->truth 0.037 /
        0.035 / 0.034 / 0.034 m; paper-like set seeds 1-4, Chamfer 24.8 / 25.5 / 26.4 / 28.1 mm.
        Tighter tangents draw planes farther past the edges MuJoCo's normals tilt.
    plane_reach_m : float
        A *lone* touch (no other event's contact within this of its own) also adds four
        contact rows this far from it along its two tangents (mixture, 3D; 0: none): the face
        goes on past the ~0.3 m a length scale alone carries it. Without them almost none of
        the true surface 0.3-0.5 m from the nearest trusted touch was meshed, 100 % of it
        beyond 0.4 m. Where other touches are that near, they speak for the surface between
        them, and plane points there only draw brims past edges: on the paper-like set
        (900 dense contacts) planes at every contact cost 6 mm of Chamfer, planes at lone ones
        none. A plane point past another touch's face or round a bend two touches show is
        left out (``training._plane_keep``). The rows belong to the touch's event, so its
        fate is theirs and free space through them is evidence against it. Tuning flights
        (seed 200, 27 flights, flight means; gusts and touches pooled), 0 with mask 0.7 ->
        0.2 with mask 0.6 (``surface.max_std_fraction``): missing within 0.5 m 0.302 ->
        0.245, within 0.2 m 0.043 -> 0.032, largest phantom patch 0.145 -> 0.122 m²,
        Chamfer 0.063 -> 0.054 m, mesh->truth 0.028 -> 0.023 m, touches flagged 14 -> 12 of
        568, gusts 114 of 117 both. Without the bend rule the simple-physics pillars' mesh->
        truth went 0.01 -> 0.03 m (drawn as boxes); with it they stay at 0.01 m. Planes at
        0.25 m drew more phantom (0.284 against 0.197 m² at 0.2 m, mask 0.7, no guards).
    plane_noise_per_m : float
        Standard deviation of a plane point's value per metre of reach (label units / m), on
        top of ``contact_noise``: at 0.2 m, 0.5 gives 0.11, a hint that a dense touch set
        overrides.
    plane_max_p_false : float
        Plane points only for a touch whose prior ``P(false)`` (the detector's ``p_false``,
        else ``prior_false``) is at most this: the surface is carried on from touches the
        detector believes. Without it, the reporting flights' contact-free controls drew
        0.4 m² patches 1.4 m from any structure around lone detector false alarms left at
        ``P(false)`` 0.49 (prior 0.41-0.53), just short of being flagged. Tuning flights
        (seed 200, flight means) 1.0 -> 0.3: largest phantom patch 0.122 -> 0.109 m²,
        missing within 0.5 m 0.245 -> 0.246, mesh->truth 0.023 -> 0.022 m, touches flagged
        12 -> 13 of 568, gusts 114 of 117 both.
    plane_guard_m : float
        A plane point that another touch within this of it places outside its own surface (in
        front of its tangent plane by more than 2 cm) is left out (``training._plane_keep``;
        0: no touch cuts one off at an edge): the other face of an edge was touched. Any touch
        counts, whatever solid it belongs to: a gust the detector believes, in the free space
        in front of a touched face, loses the points that lie in front of that face too. At
        0.8 or 1.0 m for every touch (a low box top then cuts off a wall's points above it), the
        tuning flights (seeds 200-202) lost more true surface and drew more phantom: flights
        with a largest patch over 0.1 m² 11 -> 12 of 36 gusty (both), missing by area 3.0 ->
        3.9 / 4.2 %.
    plane_guard_solid_m : float
        ... and a touch within this farther reach cuts it off where the two touches are faces
        of one solid (each on or behind the other's tangent plane; 0 or at most
        ``plane_guard_m``: no farther reach). A pier deck's side touched 7 cm above its lower
        edge put a plane point 13 cm below the deck, and the field sagged 0.2 m under it over
        the 0.8 m between two pillars, in the controls too (0.07-0.17 m²); the underside
        touched 0.7-0.9 m along says the side stops there. Tuning flights (seeds 200-202, 36
        gusty flights and their 36 controls), 0.5 -> 1.0 m: flights with a largest patch over
        0.1 m² 11 -> 7 of 36 gusty, 2 -> 0 of 36 controls (the worst control 0.174 -> 0.083
        m²); phantom area 0.213 -> 0.143 m² (mean; controls 0.117 -> 0.046); touched surface
        missing within 0.2 m by area 3.0 -> 2.8 % (controls 2.5 -> 2.0 %); gusts flagged 370
        of 372 both, touches 14 -> 15 of 811. One simple yard flight drew a new 0.26 m² bulge in
        front of a thin wall whose end face lost a plane point past its side.
    internal_guard_m : float
        An internal row (``inside_value``, ``contact.internal_depth_m`` behind a contact along
        its normal) that a touch the detector believes (prior ``P(false)`` at most
        ``plane_max_p_false``), of another event within this of it and a face of the same
        solid, places outside its own surface (in front of its tangent plane by more than 2
        cm) is left out (``training._past_edge``; 0: every internal row kept). A touch at an
        edge whose normal is tilted across it puts its internal row past the other face, in
        open space, with a value that says 'inside': the field goes negative there and the
        surface bulges round it.
    internal_guard_tilt_deg : float
        How far the detector may tilt a touch's normal when the internal guard asks whether
        two touches are faces of one solid (each on or behind the other's tangent plane,
        ``training.one_solid``): the test allows 2 cm plus their distance times the sine of
        this (0: 2 cm at any distance). On MuJoCo the normals lie 13.5 deg off (median):
        touches on a box's two faces 0.42 m apart round a corner (a dock flight of reporting
        seed 132) failed the test by 4 cm, and the internal row of one, 3 cm past the other
        face, drew a 0.10 m² bulge in front of it (0.03 m² at 15 deg). The same tolerance in
        the plane guard and the open space as well (``solid_tilt``, judged 2026-12-08) drew
        0.23-0.28 m² beside the tuning yard's sphere: the plane guard then cut points a
        curved face needs. In the internal guard alone, tuning flights (seeds 200-202, 31
        gusty flights and their 30 controls), 0 -> 10 / 15 deg: flights over 0.1 m² 1 -> 0 / 0
        (controls 1 -> 0 / 0), mean largest patch 0.0216 -> 0.0184 / 0.0186 m², touched
        surface missing within 0.2 m by area 1.90 -> 2.03 / 2.03 % (MuJoCo 3.74 -> 4.01 /
        4.02 %; one wall end, whose bulge went with its surface), flags identical. Not
        adopted: the rule allowed 0.1 point more missing.
    lone_reach_m : float
        An event no other event's contact lies within this of (its contacts' centroid) is
        *uncorroborated*, and decided on the ``mapper.lone_flag_p`` line instead of
        ``mapper.flag_p`` (mixture; 0: none is). At about two length scales, other touches no
        longer predict the surface at a contact: the data neither confirm nor refute it, and
        its posterior stays at the detector's prior. Tuning flights (seeds 200-202, 36 gusty
        flights and their 36 controls), none -> 0.5 m with ``mapper.lone_flag_p`` 0.2: largest
        phantom patch 0.134 -> 0.110 m² (mean; median 0.115 -> 0.075), gust events flagged
        356 -> 366 of 372, touches 13 of 811 and slow touches 5 of 109 both; on the controls
        slow touches 2 -> 4 of 106, missing within 0.2 m 0.018 -> 0.020.

        Only an event the map does not believe false (P(false) at most ``mapper.flag_p`` at
        the last fit; its prior when new) corroborates another: two gusts of one cluster push
        the drone to the same place, and a flagged one kept a doubted one beside it on the
        ``flag_p`` line. Tuning flights, any event -> those not believed false: largest
        phantom patch 0.110 -> 0.091 m² (mean; median 0.075 -> 0.052), gust events flagged
        366 -> 370 of 372, touches 13 -> 14 of 811, slow touches 5 of 109 both; the controls
        identical.
    model : "robust" | "gpis"
        Student-t robust GPIS (the paper's method) or homoscedastic GPIS.
    lengthscale : float
        Initial squared-exponential length scale, metres. The paper's "initial kernel
        variance 0.25^2" read as a length scale (ALGORITHM.md §1); raised to
        ``lengthscale_min`` when that is larger.
    signal_var : float
        Initial kernel signal variance sigma_f^2 (label units^2).
    alpha, beta : float
        Initial InvGamma(alpha, beta) prior on the per-datum noise variances (paper: 2, 4).
    noise_var : float
        Initial noise variance of the homoscedastic GPIS.
    prior_mean : float
        Constant GP prior mean mu0, label units (paper: 0). Where the data say nothing the
        field relaxes to it, so with mu0 = 0 the zero set lingers near every trusted contact:
        faces extended past a structure's edge, the underside of a deck drawn 0.2 m low.
        mu0 = +0.3 leans unknown space "outside" (a third of the way to a drone centre's
        +1): surface is drawn only where the data pull the field below zero. On the tuning
        flights (seed 200, 27 logs) against mu0 = 0: largest phantom patch 0.31 -> 0.15 m^2
        (gusty mean), mesh->truth median 0.045 -> 0.033 m, gusts flagged 112 -> 114 of 117,
        touched surface missing within 0.2 m 0.094 -> 0.099 and within 0.5 m 0.30 -> 0.32
        (less extrapolation round corners). The trade is monotone (mu0 = 0 / 0.15 / 0.3 / 0.5:
        phantom 0.31 / 0.23 / 0.15 / 0.10 m^2, missing within 0.5 m 0.30 / 0.31 / 0.32 / 0.35);
        0.3 has the lowest Chamfer (0.072 / 0.069 / 0.068 / 0.069 m). The legacy engine's
        comparisons pin mu0 to 0.
    open_offset : float
        The open-space offset's full value (label units; 0: none): added to the field wherever
        it is evaluated (never to the fit), 0 within ``open_start_m`` of every row the data show
        to be surface (contacts and plane points, whatever the fit decides of their events),
        the full value from ``open_end_m`` on, but only in front of the touches near a point
        (``mapping/openspace.py``). A touched face then stops near its touches instead of
        carrying on a length scale past them: a pier deck touched at mid-height on its side
        was drawn 0.13-0.26 m above its top along that edge. Tuning flights (seeds 200-202,
        36 gusty flights and their 36 controls), 0 -> 0.5 / 0.7: touched surface missing within
        0.2 m by area 2.8 -> 1.8 / 1.7 % (MuJoCo 4.3 -> 3.4 / 3.3 %; controls 2.0 -> 1.0 /
        1.0 %), largest phantom patch 0.080 / 0.042 / 0.585 -> 0.076 / 0.029 / 0.543 (0.7:
        0.075 / 0.023 / 0.529) m² (mean / median / worst), phantom area 0.127 -> 0.102 / 0.100 m²
        (controls 0.038 -> 0.027 both), flights over 0.1 m² 7 -> 7 / 8 (controls 0 -> 0 / 1),
        Chamfer near touches 42.8 -> 40.7 / 40.6 mm, mesh->truth median 19.0 -> 19.7 / 20.1 mm;
        every flag the same (the fit does not see it).
    open_start_m, open_end_m : float
        Where the offset rises with the distance to the nearest surface row, metres.
    open_reach_m, open_front_m : float
        The touches within ``open_reach_m`` decide whether a point is in front of the data
        (the full offset ``open_front_m`` in front of one's tangent plane; none within reach:
        open space); behind all of them a point is inside a structure and has none, and so is
        one deeper than ``d_in`` behind the nearest touch that no free-space sample is nearer to.
    open_solid : bool
        ... except where the point lies in front of another face of that touch's solid (a touch
        within reach, each of the two on or behind the other's tangent plane): past an edge of
        a convex solid, such as the top of a pier deck above its touched side, is open space.
        Tuning flights (seeds 200-202): missing by area 1.80 -> 1.76 %, largest patch mean
        0.076 -> 0.073 m², Chamfer 40.7 -> 40.2 mm, flags identical (README, "past an edge").
    optimize : bool
        Learn the kernel hyperparameters (M-step) or keep them at their initial values.
    noise_update : "direct" | "em"
        (alpha, beta) update: the direct maximiser (ALGORITHM.md §4.1, default) or the
        literal EM fixed point (Kuss M1/M2), which stalls from beta = 4 (§7.1).
    max_iter : int
        EM iteration limit.
    tol : float
        Relative ELBO change below which the EM counts as converged (3 iterations in a row).
    beta_floor : float
        Lower bound on beta (ALGORITHM.md §7.4).
    merge : bool
        Merge redundant observations before fitting (``mapping.merge``) once the raw set
        exceeds ``merge_min_raw``.
    merge_min_raw : int
        Below this many raw observations every one is fitted: merging drops free-space points
        that refute false contacts (on 8 SITL sessions the merged sets fell to the Gaussian
        plateau where the raw ones did not), and the exact model is cheap there (1000, the
        exact budget; 0 merges from the first fit).
    merge_voxel_factor : float
        Merge radius (voxel edge) for contacts and internal points, in length scales (the learnt
        one, rounded to a power of sqrt(2)), floored at ``merge_voxel_min``. 0.25 (was 0.125):
        paper-like set Chamfer 0.062-0.072 m on 3 seeds (0.5: 0.076-0.128 m).
    external_voxel_factor : float
        Merge radius (voxel edge) for external (free-space) points, in length scales (floored at
        the contact radius). 0.3 (was 1.0): on the paper-like set (6 seeds) one free-space cell
        per ~l merged them so far that every fit went to the Gaussian limit (Chamfer 0.24-0.5
        m); at 0.3 l every seed reached Chamfer 0.060-0.066 m with the false contacts flagged.
    suspect_u : float
        A merged cell whose ``u_i`` exceeds this (label units^2) is a suspected false contact:
        its observations are never merged with trusted ones at the next refit.
    suspect_ratio : float
        ... and whose ``u_i`` also exceeds this multiple of the contacts' median ``u``: a fit in
        a high-noise regime (every u above ``suspect_u``) must not flag every contact (seen on
        the paper-like 3D set, where it collapsed the next merge to a few coarse cells).
    exact_budget : int
        Largest merged training set fitted by the exact model; above it the sparse model runs
        (1000, was 1500: an exact EM iteration at n = 1400 cost ~3x a sparse one at M ~ 550).
    n_inducing : int
        Maximum number of inducing points of the sparse model.
    pilot_size : int
        Cold start on a merged set larger than this: the length scale is first learnt by an
        exact fit on a voxel subsample of at most this many points, the data are merged at that
        scale, and the fit warm-starts from the pilot (a cold exact fit on 1,292 merged points
        took 111 EM iterations and landed in a worse basin, ALGORITHM.md §7.6).
    refit_max_iter : int
        EM iteration limit of warm-started refits. The ELBO never decreases, so a refit cut
        short is a valid partial update that the next refit continues; it keeps the refit time
        bounded as the session grows (``converged_`` then reads False).
    merge_voxel_min : float
        Floor of the merge voxel edge, metres.
    refit_tol : float
        Relative ELBO tolerance of warm-started refits (cold fits use ``tol``).
    merge_rule : "radius" | "voxel"
        ``radius`` (default): leader clustering within ``merge_voxel_factor * l`` (floored at
        ``merge_voxel_min``), incremental between refits (``merge.StreamingMerger``); no cell
        doubling on voxel boundaries, and revisited faces add no cells. ``voxel``: per-voxel
        merge (``merge.merge_observations``), recomputed at every refit.
    merge_weight_cap : float
        A merged cell of ``c`` observations is fitted as ``min(c, merge_weight_cap)`` coincident
        observations (noise precision ``c w``, bound terms counted ``c`` times; exact for exact
        duplicates, ``RobustGPIS.fit(sample_weight=)``). Default 1 (off): with the counts the
        converged fits on the paper-like set interpolated everything (beta at its floor,
        l ~ 0.18 m, Chamfer 0.24-0.31 m), like the exact model on the raw rows (l = 0.07 m,
        Chamfer 0.20 m); a cell then counts once whatever its size.
    merge_hysteresis : float
        The merge radii are frozen once chosen and only recomputed (a full re-merge) when the
        learnt length scale moves them by more than this factor (> 1).
    theta_refit_growth : float
        Warm refits keep the kernel hyperparameters fixed (only q(tau), (alpha, beta) and q(f)
        are updated) unless the merged set has grown by more than this factor since the last
        fit that learnt them (>= 1; 1 learns them at every refit).
    gaussian_restart_alpha : float
        A fit whose alpha reached this (the Gaussian limit, every u alike, nothing flagged) is
        not warm-started at the next refit that would learn theta (``theta_refit_growth``): it
        is redone cold, since a warm start never leaves that limit (seen on the 40-min session:
        alpha = 1e6 from the first fit on, while a cold fit at 20 min gave alpha = 0.54).
    refit_u_tol : float
        Warm refits also stop once no ``log u_i`` moved by more than this in one iteration.
    blas_threads : int
        BLAS threads while fitting/evaluating (0: leave the process setting alone). One thread
        was steadier and faster than two on the loaded 2-core machines (STACK.md).
    cold_check : bool
        At warm refits of the exact model that learn the kernel hyperparameters
        (``theta_refit_growth``), also fit cold and keep the higher final ELBO
        (``SurfaceModel._cold_check``). The set grows geometrically between such refits, so
        they are rare; a cold exact fit on <= 1000 rows costs 1-4 s. Not in sparse mode: there
        a cold fit took 18-31 s on the 40-minute session (a stalled live mesh), and the sparse
        model starts from the exact model's checked state.
    inside_value : float
        Potential the estimator is given for internal points (label -1), d_in behind their
        contact. The paper's -1 makes the potential twice as steep inside (-1 at 0.1 m) as
        outside (+1 at the drone centre, >= r = 0.2 m out), so a 0.2 m wall (both faces'
        internal points at its centre) needs a length scale the gusts also fit into; -d_in/r
        = -0.5 makes the slope symmetric. Labels on the bus and in files stay -1/0/+1.
    lengthscale_min : float
        Lower bound of the learnt length scale, metres: the finest detail the map resolves
        (the initial ``lengthscale`` is raised to it). 0.1 m: twice the 0.05 m grid (the legacy
        engine was measured at 0.35 m, below). A false contact is refuted only by
        free-space points within about a length scale of it; ML-II on sparse touch data picks
        l ~ 0.16-0.2 m, where every gust is interpolated as a tiny object of its own. Measured
        on 11 SITL sessions (52 gust and 187 touch events), flagged-event precision / recall:
        0.30 m 0.88 / 0.42, 0.35 m 1.00 / 0.46, 0.40 m 0.73 / 0.58 (below 0.4 m the pier's
        0.15 m legs are finer than the map and their touches get flagged). 0.01 = no floor.
    signal_var_max : float
        Upper bound of the learnt signal variance sigma_f^2 (label units^2). Labels lie in
        [-1, 1]; a bounded length scale otherwise trades for sigma_f^2 up to ~8 (prior std
        2.8), which again interpolates every gust.
    """

    engine: Literal["mixture", "legacy"] = "mixture"
    lengthscale_max: float = 0.35
    hold_at_cap: bool = False
    outlier_var: float = 1.0
    contact_noise: float = 0.05
    free_noise: float = 0.3
    free_voxel_m: float = 0.1
    prior_false: float = 0.1
    burst_gap_s: float = 3.0
    burst_radius_m: float = 0.3
    burst_events_min: int = 3
    burst_llr: float = 3.0
    burst_min_p_false: float = 0.05
    sweep_llr: float = 4.6
    sweep_exclude_s: float = 0.5
    sweep_tolerance_m: float = 0.03
    sweep_disc_m: float = 0.1
    companion_s: float = 0.5
    body_clearance: bool = True
    flag_tol: float = 5e-3
    flag_inside: bool = False
    mixture_max_iter: int = 12
    learn_min_events: int = 3
    learn_free_reach_m: float = 0.0
    tangent_slope_noise: float = 1.0
    tile_m: float = 1.0
    learn_tile_m: float = 2.0
    kernel_block_rows: int = 1500
    settle_p_false: float = 0.05
    settle_after_s: float = 60.0
    settle_evidence_nats: float = 0.7
    settled_voxel_m: float = 0.1
    plane_reach_m: float = 0.2
    plane_noise_per_m: float = 0.5
    plane_max_p_false: float = 0.3
    plane_guard_m: float = 0.5
    plane_guard_solid_m: float = 1.0
    internal_guard_m: float = 0.5
    lone_reach_m: float = 0.5
    internal_guard_tilt_deg: float = 0.0
    model: Literal["robust", "gpis"] = "robust"
    lengthscale: float = 0.25
    signal_var: float = 1.0
    alpha: float = 2.0
    beta: float = 4.0
    noise_var: float = 0.01
    prior_mean: float = 0.3
    open_offset: float = 0.5
    open_start_m: float = 0.1
    open_end_m: float = 0.3
    open_reach_m: float = 0.8
    open_front_m: float = 0.1
    open_solid: bool = True
    optimize: bool = True
    noise_update: Literal["direct", "em"] = "direct"
    max_iter: int = 200
    tol: float = 1e-6
    beta_floor: float = 1e-6
    merge: bool = True
    merge_min_raw: int = 1000
    merge_voxel_factor: float = 0.25
    external_voxel_factor: float = 0.3
    suspect_u: float = 0.05
    suspect_ratio: float = 3.0
    exact_budget: int = 1000
    n_inducing: int = 600
    pilot_size: int = 600
    refit_tol: float = 1e-5
    refit_max_iter: int = 15
    merge_voxel_min: float = 0.1
    blas_threads: int = 1
    merge_rule: Literal["radius", "voxel"] = "radius"
    merge_hysteresis: float = 2.0
    merge_weight_cap: float = 1.0
    theta_refit_growth: float = 1.25
    refit_u_tol: float = 0.1
    gaussian_restart_alpha: float = 1e5
    cold_check: bool = True
    inside_value: float = -0.5
    lengthscale_min: float = 0.1
    signal_var_max: float = 1.0

    def __post_init__(self) -> None:
        for name in (
            "lengthscale",
            "signal_var",
            "alpha",
            "beta",
            "noise_var",
            "tol",
            "merge_voxel_factor",
            "external_voxel_factor",
            "suspect_u",
            "suspect_ratio",
            "refit_tol",
            "merge_voxel_min",
            "refit_u_tol",
            "gaussian_restart_alpha",
            "lengthscale_min",
            "signal_var_max",
            "lengthscale_max",
            "outlier_var",
            "contact_noise",
            "free_noise",
            "free_voxel_m",
            "burst_radius_m",
            "flag_tol",
            "settled_voxel_m",
            "tile_m",
            "learn_tile_m",
        ):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"mapping.{name} must be > 0, got {value!r}")
        if self.engine not in ("mixture", "legacy"):
            raise ValueError(f"mapping.engine must be mixture or legacy, got {self.engine!r}")
        if not self.lengthscale_min <= self.lengthscale_max:
            raise ValueError(
                f"mapping.lengthscale_min {self.lengthscale_min!r} must not exceed "
                f"lengthscale_max {self.lengthscale_max!r}"
            )
        if not 0 <= self.settle_p_false < 0.5:
            raise ValueError(
                f"mapping.settle_p_false must be in [0, 0.5), got {self.settle_p_false!r}"
            )
        if not 0 < self.prior_false < 1:
            raise ValueError(f"mapping.prior_false must be in (0, 1), got {self.prior_false!r}")
        if not 0 <= self.burst_min_p_false <= 1:
            raise ValueError(
                f"mapping.burst_min_p_false must be in [0, 1], got {self.burst_min_p_false!r}"
            )
        if not 0 <= self.plane_max_p_false <= 1:
            raise ValueError(
                f"mapping.plane_max_p_false must be in [0, 1], got {self.plane_max_p_false!r}"
            )
        for name in (
            "burst_gap_s",
            "sweep_llr",
            "sweep_exclude_s",
            "sweep_tolerance_m",
            "sweep_disc_m",
            "companion_s",
            "burst_llr",
            "settle_after_s",
            "settle_evidence_nats",
            "lone_reach_m",
            "learn_free_reach_m",
            "plane_guard_m",
            "plane_guard_solid_m",
            "internal_guard_m",
        ):
            if not getattr(self, name) >= 0:
                raise ValueError(f"mapping.{name} must be >= 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.open_start_m < self.open_end_m:
            raise ValueError(
                "mapping.open_start_m and open_end_m must satisfy 0 <= start < end, "
                f"got {self.open_start_m!r}, {self.open_end_m!r}"
            )
        if not (self.open_offset >= 0 and self.open_reach_m > 0 and self.open_front_m > 0):
            raise ValueError(
                "mapping.open_offset must be >= 0 and open_reach_m, open_front_m > 0, got "
                f"{self.open_offset!r}, {self.open_reach_m!r}, {self.open_front_m!r}"
            )
        if not 0.0 <= self.internal_guard_tilt_deg < 90.0:
            raise ValueError(
                "mapping.internal_guard_tilt_deg must be in [0, 90) degrees, got "
                f"{self.internal_guard_tilt_deg!r}"
            )
        if not -1.0 <= self.inside_value < 0.0:
            raise ValueError(f"mapping.inside_value must be in [-1, 0), got {self.inside_value!r}")
        if not self.lengthscale_min < 100.0:
            raise ValueError(
                f"mapping.lengthscale_min must be < 100 m, got {self.lengthscale_min!r}"
            )
        if not self.signal_var_max > 1e-3:
            raise ValueError(f"mapping.signal_var_max must be > 1e-3, got {self.signal_var_max!r}")
        if self.merge_rule not in ("radius", "voxel"):
            raise ValueError(
                f"mapping.merge_rule must be 'radius' or 'voxel', got {self.merge_rule!r}"
            )
        if not self.merge_weight_cap >= 1.0:
            raise ValueError(
                f"mapping.merge_weight_cap must be >= 1, got {self.merge_weight_cap!r}"
            )
        if not self.merge_hysteresis > 1.0:
            raise ValueError(f"mapping.merge_hysteresis must be > 1, got {self.merge_hysteresis!r}")
        if not self.theta_refit_growth >= 1.0:
            raise ValueError(
                f"mapping.theta_refit_growth must be >= 1, got {self.theta_refit_growth!r}"
            )
        if self.max_iter < 1:
            raise ValueError(f"mapping.max_iter must be >= 1, got {self.max_iter!r}")
        for name, low in (
            ("exact_budget", 2),
            ("n_inducing", 2),
            ("pilot_size", 2),
            ("refit_max_iter", 1),
            ("mixture_max_iter", 1),
            ("learn_min_events", 1),
            ("kernel_block_rows", 0),
            ("burst_events_min", 2),
            ("blas_threads", 0),
            ("merge_min_raw", 0),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"mapping.{name} must be an integer >= {low}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class SurfaceSettings:
    """Where and how finely the field is evaluated and meshed.

    Attributes
    ----------
    region_min, region_max : tuple of float
        An optional clip of the mapped region, metres (empty: none). The region follows the
        data: the box of every observation (contacts, internal points and the path flown) plus
        ``region_margin``; a configured clip that cuts into it is reported with each fit
        (``region_clipped``).
    spacing : float
        Grid spacing, metres (paper: 0.05 m in 3D, 0.02 m in 2D).
    chunk_mb : float
        Memory budget of one prediction chunk, MB.
    voxels_per_lengthscale : float
        The mesh grid spacing is ``max(spacing, l / voxels_per_lengthscale)`` with the learnt
        length scale l: the field has no detail below l, so ``spacing`` is only a floor.
    coarse_factor : int
        Stride (in fine voxels) of the first coarse pass of the narrow-band evaluation; 1
        evaluates the whole grid.
    band_voxels : float
        Half-width, in fine voxels, of the band around the zero set evaluated exactly.
    region_margin : float
        Metres added around the data's bounding box (mixture: every observation; legacy: the
        contacts); a configured ``[region_min, region_max]`` clips it.
    max_std_fraction : float
        Keep only mesh faces whose vertices' predictive std is at most this fraction of the
        prior std sigma_f (``surface.confident_part``); 1 keeps everything. Far from the
        observations the mean relaxes to the prior mean and its zero set says nothing. The
        one knob between surface missing and phantom surface: on the tuning flights (seed
        200, flight means) without plane points, 0.6 / 0.7 / 0.85 / 1.0 gave missing within
        0.5 m 0.357 / 0.302 / 0.221 / 0.186 and largest phantom patch 0.102 / 0.145 / 0.227
        / 0.407 m². With ``mapping.plane_reach_m`` 0.2, 0.6 gives 0.245 and 0.122 m², both
        better than 0.7 without planes (see there). A mask on the zero set's position std
        (std / |gradient|) instead was tried at 0.10 / 0.15 / 0.20 m: 0.360 / 0.280 / 0.235
        missing against 0.116 / 0.198 / 0.233 m², a worse trade than this one. The legacy
        engine was measured at 0.7 (``bench pareto``'s legacy settings pin it).
    drop_cavities : bool
        Drop the inward-facing shells the field draws deep inside a structure touched all
        round (``mapping/cavities.py``; mixture engine). On the dense 40-minute session
        (l = 0.1 m) the inside of the box was the map's largest phantom patch, 2.8 m² at 30
        min (0.23 m² without it); on the tuning flights and the paper-like 3D set
        (l = 0.23-0.3 m) nothing is a cavity.
    """

    region_min: tuple[float, ...] = ()
    region_max: tuple[float, ...] = ()
    spacing: float = 0.05
    chunk_mb: float = 64.0
    voxels_per_lengthscale: float = 5.0
    coarse_factor: int = 4
    band_voxels: float = 2.0
    region_margin: float = 0.5
    max_std_fraction: float = 0.6
    drop_cavities: bool = True

    def __post_init__(self) -> None:
        if len(self.region_min) != len(self.region_max) or len(self.region_min) not in (0, 2, 3):
            raise ValueError(
                f"surface.region_min/region_max must both be empty or have 2 or 3 coordinates, got "
                f"{self.region_min!r} and {self.region_max!r}"
            )
        if any(hi <= lo for lo, hi in zip(self.region_min, self.region_max, strict=True)):
            raise ValueError(
                f"surface.region_max {self.region_max!r} must exceed region_min {self.region_min!r}"
            )
        if not self.spacing > 0:
            raise ValueError(f"surface.spacing must be > 0, got {self.spacing!r}")
        if not self.chunk_mb > 0:
            raise ValueError(f"surface.chunk_mb must be > 0, got {self.chunk_mb!r}")
        if not self.voxels_per_lengthscale > 0:
            raise ValueError(
                f"surface.voxels_per_lengthscale must be > 0, got {self.voxels_per_lengthscale!r}"
            )
        cf = self.coarse_factor
        if isinstance(cf, bool) or not isinstance(cf, int) or cf < 1 or cf & (cf - 1):
            raise ValueError(f"surface.coarse_factor must be a power of two >= 1, got {cf!r}")
        if not self.band_voxels >= 0:
            raise ValueError(f"surface.band_voxels must be >= 0, got {self.band_voxels!r}")
        if not self.region_margin >= 0:
            raise ValueError(f"surface.region_margin must be >= 0 m, got {self.region_margin!r}")
        if not 0 < self.max_std_fraction <= 1:
            raise ValueError(
                f"surface.max_std_fraction must be in (0, 1], got {self.max_std_fraction!r}"
            )


@dataclasses.dataclass(frozen=True)
class MapperSettings:
    """Refit schedule, flag rule and failure handling of the mapper.

    Attributes
    ----------
    refit_period_s : float
        Refit after this much data time since the last fit's data (seconds).
    refit_min_new : int
        ... or after this many new observations, whichever comes first.
    refit_on_contact : bool
        ... or as soon as a new contact observation and its internal point arrived (a touch
        reaches the mesh one refit after it is published, not up to a period later).
    min_contacts : int
        Contact observations needed before the first fit.
    flag_p : float
        An event is decided false when its posterior probability of being false exceeds this
        (mixture engine): flagged, and left out of the map. One threshold for both: before,
        the map left events out above 1/2 whatever this was, and drew events it flagged.
        1/2 minimises errors for equal costs.
    lone_flag_p : float
        The line for an uncorroborated event (``mapping.lone_reach_m``): nothing in the data
        speaks for or against it, so its posterior is the detector's prior, and the two errors
        cost differently there. A false contact trusted draws a whole phantom patch (its tangent
        plane spread to ``mapping.plane_reach_m``) that nothing near bounds; a true one dropped
        loses that touch until the next touch beside it corroborates it, which then puts both
        on the ``flag_p`` line. 0.2 weighs the first four times the second. Equal to
        ``flag_p``: no difference.
    flag_u : float
        Margin of the flag rule above the fit's noise floor, label units^2 (legacy engine).
    flag_event_fraction : float
        Fraction of an event's contacts that must be suspect to flag the whole event.
    flag_fraction_max : float
        More suspect contacts than this fraction makes the fit unreliable (the model rejects
        the data instead of fitting it). 0.9: a gusty session legitimately reaches 0.86.
    expect_outliers : bool
        ``diagnose``: treat the Gaussian plateau (alpha at its bound) as a failure. Off by
        default: a session with no false contact legitimately sits there.
    fallback : bool
        Try the diagnosed fallback refit when a fit is unreliable.
    with_mesh : bool
        Extract the mesh on every refit (off: only ``u`` and flags).
    """

    refit_period_s: float = 2.0
    refit_min_new: int = 30
    refit_on_contact: bool = True
    min_contacts: int = 2
    flag_p: float = 0.5
    lone_flag_p: float = 0.2
    flag_u: float = 0.3
    flag_event_fraction: float = 0.5
    flag_fraction_max: float = 0.9
    expect_outliers: bool = False
    fallback: bool = True
    with_mesh: bool = True

    def __post_init__(self) -> None:
        for name in ("refit_period_s", "flag_u"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"mapper.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("refit_min_new", "min_contacts"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"mapper.{name} must be an integer >= 1, got {v!r}")
        for name in ("flag_p", "lone_flag_p"):
            if not 0 < getattr(self, name) < 1:
                raise ConfigError(f"mapper.{name} must be in (0, 1), got {getattr(self, name)!r}")
        for name in ("flag_event_fraction", "flag_fraction_max"):
            if not 0 < getattr(self, name) <= 1:
                raise ConfigError(f"mapper.{name} must be in (0, 1], got {getattr(self, name)!r}")
