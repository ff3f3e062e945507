"""Map engine v2: observations -> rows and events -> event-mixture GP -> region -> mesh (pure).

:class:`SurfaceModel` is what the mapper fits at every refit. Its :meth:`SurfaceModel.fit` is a
sequence of named policy steps:

1. :meth:`~SurfaceModel.rows`: observations to rows, event groups with their detector priors,
   bursts and the swept-volume evidence (``mapping/training.py``);
2. :meth:`~SurfaceModel.learn_kernel_now`: the kernel hyperparameters are learnt once the data
   identify them (``learn_min_events`` trusted events in the learning tile; until then the
   configured ones hold) and again whenever the rows grew by ``theta_refit_growth`` since they
   last were (a covered structure stops growing, so its refits keep them);
3. :meth:`~SurfaceModel.warm_start`: every event starts from its posterior of the last fit (new
   ones from their prior), so a refit moves only what the new data moves;
4. :meth:`~SurfaceModel.estimate`: the event-mixture EM (``mapping/mixture.py``), at most
   ``refit_max_iter`` iterations when warm (``max_iter`` cold);
5. :meth:`~SurfaceModel.settle`: events trusted for ``settle_after_s`` are settled, their rows
   pooled per voxel from the next fit on (rows then grow with the area touched, not with the
   time spent touching it);
6. :meth:`~SurfaceModel.open_space`: the offset added to the field wherever it is evaluated,
   never to the fit (``mapping/openspace.py``, ``mapping.open_offset``; 0: none);

and :meth:`SurfaceModel.mesh` evaluates the field in a narrow band around its zero set on a grid
over the *data's* region (:meth:`~SurfaceModel.region`: every observation plus a margin, clipped
only by a configured region, which is then reported), runs marching cubes, keeps the faces
whose predictive std is at most ``max_std_fraction`` of the prior std and drops the cavities
drawn inside structures touched all round (``mapping/cavities.py``).

Pure: no clock reads except the ``timings_`` it reports, no files, no threads.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from groundstation.contact.detector import Observation
from groundstation.contact.vehicle import VehicleSettings
from groundstation.errors import ConfigError, InputDataError, NotFittedError
from groundstation.mapping._linalg import blas_threads
from groundstation.mapping.cavities import cavity_faces
from groundstation.mapping.field import narrow_band_field
from groundstation.mapping.grid import Grid
from groundstation.mapping.mixture import EventMixtureGPIS, Groups, KernelBounds, MixtureFit
from groundstation.mapping.openspace import OpenSpaceOffset
from groundstation.mapping.settings import MappingSettings, SurfaceSettings
from groundstation.mapping.surface import (
    SurfaceMesh,
    confident_part,
    extract_surface,
    weld_lattice,
)
from groundstation.mapping.tiles import TileLayout, signature
from groundstation.mapping.training import TrainingPolicy, TrainingSet, build_training_set

#: The surface is drawn up to this many length scales from an anchor
#: (:meth:`SurfaceModel.reach_m`).
REACH_LENGTHSCALES = 2.5
#: A face deeper than this many internal-point depths behind its nearest touch, facing away
#: from it, may be a cavity's (``mapping/cavities.py``); internal points lie one depth behind.
CAVITY_DEPTH_INTERNALS = 1.5
#: The kernel's learning tile holds at least this halo, metres: at l = 0.1 m a halo of 3 l
#: left too little surface there to learn it from (the bundled wall survey's final map became
#: worse than its live one, 853585c).
LEARN_HALO_MIN_M = 0.75

_DEFAULT_MAPPING = MappingSettings()
_DEFAULT_SURFACE = SurfaceSettings()


def kernel_bounds(mapping: MappingSettings) -> KernelBounds:
    """The kernel bounds of the settings (resolution floor and cap, signal variance range)."""
    return KernelBounds(
        lengthscale=(mapping.lengthscale_min, mapping.lengthscale_max),
        signal_var=(min(0.05, mapping.signal_var_max), mapping.signal_var_max),
    )


def training_policy(
    mapping: MappingSettings, vehicle: VehicleSettings, d_in: float
) -> TrainingPolicy:
    """How observations become rows (``mapping/training.py``) for these settings and body."""
    return TrainingPolicy(
        inside_value=mapping.inside_value,
        internal_depth_m=d_in,
        contact_noise=mapping.contact_noise,
        free_noise=mapping.free_noise,
        free_voxel_m=mapping.free_voxel_m,
        prior_false=mapping.prior_false,
        burst_gap_s=mapping.burst_gap_s,
        burst_radius_m=mapping.burst_radius_m,
        body_radius_m=vehicle.inner_radius_m,
        body_half_height_m=vehicle.inner_half_height_m,
        body_reach_m=vehicle.reach_m,
        tolerance_along_normal=vehicle.shape == "guards",
        sweep_exclude_s=mapping.sweep_exclude_s,
        sweep_tolerance_m=mapping.sweep_tolerance_m,
        sweep_llr=mapping.sweep_llr,
        sweep_disc_m=mapping.sweep_disc_m,
        burst_events_min=mapping.burst_events_min,
        burst_llr=mapping.burst_llr,
        burst_min_p_false=mapping.burst_min_p_false,
        tangent_slope_noise=mapping.tangent_slope_noise,
        plane_reach_m=mapping.plane_reach_m,
        plane_noise_per_m=mapping.plane_noise_per_m,
        plane_max_p_false=mapping.plane_max_p_false,
        plane_guard_m=mapping.plane_guard_m,
        plane_guard_solid_m=mapping.plane_guard_solid_m,
        internal_guard_m=mapping.internal_guard_m,
        settled_voxel_m=mapping.settled_voxel_m,
        companion_s=mapping.companion_s,
        body_clearance=mapping.body_clearance,
        lone_reach_m=mapping.lone_reach_m,
        internal_guard_tilt_deg=mapping.internal_guard_tilt_deg,
    )


def _or_none(a: np.ndarray | None) -> np.ndarray:
    """``a``, or an empty array for None (a tile signature hashes arrays)."""
    return np.zeros(0, dtype=np.int64) if a is None else a


@dataclasses.dataclass(frozen=True)
class Region:
    """The mapped region.

    Attributes
    ----------
    lo, hi : (d,) float64, metres
        What is meshed.
    data_lo, data_hi : (d,) float64
        The data's box plus the margin (before any configured clip).
    clipped : bool
        A configured region cut into the data's box.
    """

    lo: np.ndarray
    hi: np.ndarray
    data_lo: np.ndarray
    data_hi: np.ndarray
    clipped: bool


class SurfaceModel:
    """Map engine v2 (see the module docstring).

    Parameters
    ----------
    mapping : MappingSettings
    surface : SurfaceSettings
    vehicle : VehicleSettings
        The body whose swept volume refutes contacts.
    internal_depth_m : float
        ``d_in`` of the detector (the slope of the potential behind a contact).
    decide_p : float
        An event whose posterior P(false) exceeds this is decided false: left out of the map
        and flagged (the mapper passes ``mapper.flag_p``: one rule for both).
    lone_decide_p : float
        The line for an *uncorroborated* event instead, one no other event's contact lies
        within ``mapping.lone_reach_m`` of (the mapper passes ``mapper.lone_flag_p``). Nothing
        in the data speaks for or against such an event, so its posterior is its prior, and
        the costs of the two errors differ: a false one trusted draws a whole phantom patch
        with no surface near to bound it, a true one dropped loses one touch until the next
        touch beside it corroborates it (and both are then decided on the ``decide_p`` line).
        Only an event not believed false (P(false) at most ``decide_p`` at the last fit, its
        prior when new) corroborates another.

    Attributes (after ``fit``)
    --------------------------
    fit_ : EventMixtureGPIS
    summary_ : MixtureFit
    training_set_ : TrainingSet
    posterior_false_ : (G,) float64
        Each event's posterior P(false).
    decided_false_ : (G,) bool
        Each event's decision: its posterior above its line (``decide_p`` or ``lone_decide_p``).
    mode_ : "exact"
    timings_ : dict
        ``rows_s``, ``fit_s`` (last fit), ``mesh_s`` (last mesh) and, of it, ``mesh_gp_s`` (the
        tiles' GP means) and ``mesh_offset_s`` (the open-space offset), seconds.
    """

    def __init__(
        self,
        mapping: MappingSettings = _DEFAULT_MAPPING,
        surface: SurfaceSettings = _DEFAULT_SURFACE,
        vehicle: VehicleSettings | None = None,
        internal_depth_m: float = 0.1,
        decide_p: float = 0.5,
        lone_decide_p: float | None = None,
    ) -> None:
        lone_decide_p = decide_p if lone_decide_p is None else lone_decide_p
        for name, v in (("decide_p", decide_p), ("lone_decide_p", lone_decide_p)):
            if not 0.0 < v < 1.0:
                raise ConfigError(f"{name} must be in (0, 1), got {v!r}")
        self.mapping = mapping
        self.decide_p = float(decide_p)
        self.lone_decide_p = float(lone_decide_p)
        self.surface = surface
        self.vehicle = vehicle or VehicleSettings()
        self.policy = training_policy(mapping, self.vehicle, internal_depth_m)
        self.bounds = kernel_bounds(mapping)
        self.fit_: EventMixtureGPIS | None = None
        self.summary_: MixtureFit | None = None
        self.mode_ = "exact"
        self.timings_: dict[str, float] = {}
        self._posterior_by_event: dict[tuple, float] = {}
        self._theta: tuple[float, float] | None = None
        self._n_theta = 0  # rows at the last fit that learnt the kernel (0: never learnt)
        self._held = False  # the last kernel step asked for the cap and was not taken
        self._tiles: dict[tuple, _TileFit] = {}
        self._layout = TileLayout(mapping.tile_m, 0.0)
        self._settled: set[tuple] = set()
        self.offset_ = OpenSpaceOffset.none()
        self._mesh_clock: dict[str, float] = {}  # seconds of the mesh being drawn, by part

    # ------------------------------------------------------------------ policy steps

    def rows(self, observations: Sequence[Observation]) -> TrainingSet:
        """Step 1: rows, groups, priors, bursts, swept-volume evidence, each event's decision
        line; settled events pooled, except those the vehicle's body has since passed through
        (they are tested again)."""
        ts = build_training_set(observations, self.policy, frozenset(self._settled))
        refuted = [ts.keys[g] for g in np.flatnonzero(ts.settled & ts.swept)]
        if refuted:
            self._settled.difference_update(refuted)
            ts = build_training_set(observations, self.policy, frozenset(self._settled))
        vouch = self.warm_start(ts) <= self.decide_p  # not believed false: may corroborate
        line = np.where(ts.uncorroborated(vouch), self.lone_decide_p, self.decide_p)
        return dataclasses.replace(ts, groups=dataclasses.replace(ts.groups, decide_p=line))

    def open_space(self, ts: TrainingSet) -> OpenSpaceOffset:
        """Step 6: the open-space offset the field is evaluated with (``mapping/openspace.py``),
        from every contact and plane point (whatever the fit decided of its event) and the
        touches' normals. It never enters the fit."""
        ms = self.mapping
        if ms.open_offset == 0.0:
            return OpenSpaceOffset.none()
        value = np.einsum("ij,ij->i", ts.directions, ts.directions) == 0.0
        surface = value & (ts.y == 0.0)
        touch = surface & (np.einsum("ij,ij->i", ts.normals, ts.normals) > 0.0)
        return OpenSpaceOffset(
            ms.open_offset, ms.open_start_m, ms.open_end_m, ts.X[surface],
            ts.X[touch], ts.normals[touch], reach_m=ms.open_reach_m, front_m=ms.open_front_m,
            inside_m=self.policy.internal_depth_m, free=ts.X[ts.y > 0.0], solid=ms.open_solid,
        )  # fmt: skip

    def learn_kernel_now(self, ts: TrainingSet) -> bool:
        """Step 2: learn the kernel until it has been learnt once (:meth:`estimate` decides
        whether the data identify it yet) and then when the rows grew markedly."""
        ms = self.mapping
        if not ms.optimize:
            return False
        return self._n_theta == 0 or len(ts) > ms.theta_refit_growth * self._n_theta

    def warm_start(self, ts: TrainingSet) -> np.ndarray:
        """Step 3: each event's posterior from the last fit, its prior when new."""
        start = ts.groups.prior_false.copy()
        for g in range(start.size):
            p = self._posterior_by_event.get(ts.keys[g])
            if p is not None:
                start[g] = p
        return start

    def _estimator(self, learn: bool, warm: bool) -> EventMixtureGPIS:
        ms = self.mapping
        ell, sf2 = self._theta
        return EventMixtureGPIS(
            lengthscale=ell,
            signal_var=sf2,
            bounds=self.bounds,
            outlier_var=ms.outlier_var,
            prior_mean=ms.prior_mean,
            learn_kernel=learn,
            max_iter=ms.refit_max_iter if warm else ms.mixture_max_iter,
            tol=ms.flag_tol,
            kernel_block_rows=ms.kernel_block_rows,
            flag_inside=ms.flag_inside,
            chunk_mb=self.surface.chunk_mb,
            decide_p=self.decide_p,
        )

    @staticmethod
    def _local_groups(ts: TrainingSet, rows: np.ndarray):
        """The groups of the rows ``rows`` re-indexed: (each row's local group, the local groups'
        global indices, each row's local companion or None)."""
        rg = ts.groups.row_group[rows]
        gidx = np.unique(rg[rg >= 0])
        local = np.full(ts.groups.prior_false.size, -1, dtype=np.int64)
        local[gidx] = np.arange(gidx.size)
        comp = ts.groups.companion
        if comp is not None:
            comp = comp[rows]
            comp = np.where(comp >= 0, local[np.maximum(comp, 0)], -1)  # -1: group not here
        return np.where(rg >= 0, local[np.maximum(rg, 0)], -1), gidx, comp

    def _subset(self, ts: TrainingSet, rows: np.ndarray, start: np.ndarray):
        """The rows ``rows`` with their groups re-indexed: (X, y, s2, dirs, Groups, start, gidx)."""
        rg, gidx, comp = self._local_groups(ts, rows)
        groups = Groups(
            row_group=rg,
            prior_false=ts.groups.prior_false[gidx],
            burst=ts.groups.burst[gidx],
            extra_llr=ts.groups.extra_llr[gidx],
            companion=comp,
            decide_p=ts.groups.lines(self.decide_p)[gidx],
        )
        return (
            ts.X[rows],
            ts.y[rows],
            ts.noise_var[rows],
            ts.directions[rows],
            groups,
            start[gidx],
            gidx,
        )

    def estimate(self, ts: TrainingSet, start: np.ndarray, learn: bool) -> tuple[np.ndarray, bool]:
        """Step 4: the event-mixture EM, tile by tile (``mapping/tiles.py``): only tiles whose
        rows, priors or decisions changed are refitted. Returns the posterior P(false) of every
        group (from the tile holding its contacts' centroid) and whether the kernel was learnt.

        A kernel step needs ``learn_min_events`` events the data trust (P(false) <= decide_p) in the
        learning tile; with fewer the kernel holds. Free space alone (every row +1) is fitted
        best by the smoothest field, so a kernel learnt on one touch amid free space went to
        the 0.5 m cap, and the touch was then flagged for being alone (issue 13, Build point 6:
        three contact-free tuning flights lost their only touch and their whole map)."""
        warm = self._theta is not None
        if self._theta is None:
            ms = self.mapping
            self._theta = self.bounds.clip(max(ms.lengthscale, ms.lengthscale_min), ms.signal_var)
        shape = ts.y <= 0.0  # contact, internal and tangent rows (pooled or in a group)
        if learn:  # theta is shared by every tile: learnt where the most surface is
            region = self._learning_layout()
            key = self._learning_tile(ts, start, region)
            rows = self._learning_rows(ts, region.members(ts.X, key))
            X, y, s2, V, groups, st, _ = self._subset(ts, rows, start)
            # the kernel step weighs each row by its event's decision: decide the events that
            # are new since the last fit with the current kernel first, so that a gust still
            # at its prior does not pull the kernel smoother (and the kernel learnt does not
            # depend on how many fits came before: live cadence or --map final)
            learn = self._identified(st, groups)
            if learn:
                pre = self._estimator(False, warm).fit(X, y, s2, groups, start=st, directions=V)
                st = pre.posterior_false_
                learn = self._identified(st, groups)
            if learn:  # only the kernel: every tile refits with it below
                theta = self._estimator(True, warm).learn_theta(
                    X, y, s2, groups, start=st, directions=V
                )
                capped = "lengthscale_upper" in self.bounds.at_bound(*theta)
                self._held = capped and self.mapping.hold_at_cap
                if not self._held:
                    self._theta = theta
                    self._tiles = {}  # a new kernel: every tile refits and re-meshes
        layout = self._fitting_layout()
        # every tile the surface can reach, also one with no shape row in its own core
        near = layout.keys_near(ts.X[shape], REACH_LENGTHSCALES * self._theta[0])
        tile_keys = {tuple(int(v) for v in k) for k in near}
        decided = start > ts.groups.lines(self.decide_p)
        fitted: dict[tuple, _TileFit] = {}
        keys = sorted(tile_keys)
        for key, rows in layout.members_of(ts.X, keys).items():
            if rows.size < 2 or not shape[rows].any():
                continue  # no surface can be drawn in this core from its rows
            rg, gidx, comp = self._local_groups(ts, rows)
            sig = signature(ts.X[rows], ts.y[rows], ts.noise_var[rows], ts.directions[rows], rg,
                            np.round(ts.groups.prior_false[gidx], 4), ts.groups.burst[gidx],
                            ts.groups.extra_llr[gidx], decided[gidx], _or_none(comp))  # fmt: skip
            old = self._tiles.get(key)
            if old is not None and old.signature == sig:  # same data; rows renumbered since
                fitted[key] = dataclasses.replace(old, rows=rows, gidx=gidx)
                continue
            X, y, s2, V, groups, st, gidx = self._subset(ts, rows, start)
            est = self._estimator(False, warm).fit(X, y, s2, groups, start=st, directions=V)
            fitted[key] = _TileFit(key, rows, gidx, sig, est, None)
        self._tiles = fitted
        self._layout = layout
        post = start.copy()  # a settled group (no rows, in no tile) keeps its posterior
        owner = self._group_owner(ts, layout)
        for g in range(post.size):
            tile = fitted.get(owner[g])
            if tile is None or g not in tile.local:
                tile = next((f for f in fitted.values() if g in f.local), None)
            if tile is not None:
                post[g] = tile.est.posterior_false_[tile.local[g]]
        return post, learn

    def _fitting_layout(self) -> TileLayout:
        """Tiles of ``tile_m`` or three length scales, whichever is longer, each with a halo of
        three length scales: a tile's model then answers for its core as a model of everything
        would (the SE kernel's correlation at 3 l is 1 %), on the fewest rows. With surface
        data the rows of a tile grow with the square of (edge + 2 halo) and the tiles a change
        touches with its cube over the edge, so refits cost least near edge = halo."""
        ell = self._theta[0]
        return TileLayout(max(self.mapping.tile_m, 3.0 * ell), 3.0 * ell)

    def _learning_layout(self) -> TileLayout:
        """The region the kernel is learnt on: ``learn_tile_m`` cubes with a halo of three length
        scales but at least ``LEARN_HALO_MIN_M`` (enough surface to identify it)."""
        ell = self._theta[0]
        return TileLayout(self.mapping.learn_tile_m, max(LEARN_HALO_MIN_M, 3.0 * ell))

    def _identified(self, p_false: np.ndarray, groups: Groups) -> bool:
        """Whether events with these P(false) identify the kernel (``learn_min_events``
        decided true)."""
        trusted = p_false <= groups.lines(self.decide_p)
        return int(np.sum(trusted)) >= self.mapping.learn_min_events

    def _learning_rows(self, ts: TrainingSet, rows: np.ndarray) -> np.ndarray:
        """The rows of the learning tile the kernel step sees: every shape row, and the
        free-space rows within ``learn_free_reach_m`` of one (all of them with 0)."""
        reach = self.mapping.learn_free_reach_m
        free = ts.y[rows] > 0.0
        if reach <= 0.0 or free.all() or not free.any():
            return rows
        near = cKDTree(ts.X[rows[~free]]).query(ts.X[rows[free]], distance_upper_bound=reach)[0]
        keep = ~free
        keep[np.flatnonzero(free)[np.isfinite(near)]] = True
        return rows[keep]

    @staticmethod
    def _learning_tile(ts: TrainingSet, start: np.ndarray, layout: TileLayout) -> tuple:
        """The tile whose core holds the most surface evidence: shape rows (contact, internal,
        tangent) weighted by their event's current belief of being true, 1 - P(false).

        Counting every shape row picked, on a MuJoCo wall flight, the tile where a gust
        cluster pushed the drone (24 rows of flagged gusts against 18 of touches): its
        evidence, free space and a few contacts, rose without bound in l, and the whole map
        was meshed at the 0.5 m cap (a 0.2 m wall drawn 0.1 m too thick; 36 % of the touched
        surface missing, against none in the same flight without gusts)."""
        rg = ts.groups.row_group
        trust = np.ones(len(ts))
        ok = rg >= 0
        trust[ok] = 1.0 - start[rg[ok]]
        shape = ts.y <= 0.0
        uniq, inv = np.unique(layout.keys(ts.X[shape]), axis=0, return_inverse=True)
        weight = np.bincount(inv.reshape(-1), weights=trust[shape], minlength=len(uniq))
        return tuple(int(v) for v in uniq[int(np.argmax(weight))])

    @staticmethod
    def _group_owner(ts: TrainingSet, layout: TileLayout) -> list[tuple]:
        """The tile of each group's row centroid (its contacts and internal points)."""
        rg = ts.groups.row_group
        out = []
        sums = np.zeros((ts.groups.prior_false.size, ts.X.shape[1]))
        cnt = np.zeros(ts.groups.prior_false.size)
        ok = rg >= 0
        np.add.at(sums, rg[ok], ts.X[ok])
        np.add.at(cnt, rg[ok], 1.0)
        cent = sums / np.maximum(cnt, 1.0)[:, None]
        for k in layout.keys(cent):
            out.append(tuple(int(v) for v in k))
        return out

    # ------------------------------------------------------------------ fit

    def fit(self, observations: Sequence[Observation], learn_kernel: bool = False) -> MixtureFit:
        """Fit to every observation so far (module docstring); returns the fit summary.
        ``learn_kernel``: learn the kernel at this fit whatever step 2 says (if
        ``mapping.optimize``).

        Raises
        ------
        InputDataError
            Fewer than two observations, or nothing to fit a surface to.
        """
        with blas_threads(self.mapping.blas_threads):
            t0 = time.perf_counter()
            ts = self.rows(observations)
            if len(ts) < 2 or ts.groups.prior_false.size == 0:
                raise InputDataError("need at least one contact and one other observation")
            learn = self.learn_kernel_now(ts) or (learn_kernel and self.mapping.optimize)
            start = self.warm_start(ts)
            t1 = time.perf_counter()
            post, learnt = self.estimate(ts, start, learn)
            t2 = time.perf_counter()
            self.settle(ts, post, max(int(o.t_ns) for o in observations))
        if learnt:
            self._n_theta = len(ts)
        self.training_set_ = ts
        self.offset_ = self.open_space(ts)
        self.posterior_false_ = post
        self.decided_false_ = post > ts.groups.lines(self.decide_p)
        self._posterior_by_event = {ts.keys[g]: float(p) for g, p in enumerate(post)}
        fits = [f.est.fit_ for f in self._tiles.values()]
        ell, sf2 = self._theta
        self.summary_ = MixtureFit(
            lengthscale=ell,
            signal_var=sf2,
            log_marginal=float(sum(f.log_marginal for f in fits)),
            n_iter=max((f.n_iter for f in fits), default=0),
            converged=all(f.converged for f in fits),
            at_bounds=self.bounds.at_bound(ell, sf2),
            n_train=len(ts),
            n_groups=int(post.size),
            n_flagged=int(np.sum(self.decided_false_)),
            reasons=() if all(f.converged for f in fits) else ("not_converged",),
            kernel_held=self._held,
        )
        self.fit_ = self  # fitted marker (the tiles hold the estimators)
        self.timings_ = {
            "rows_s": t1 - t0,
            "fit_s": t2 - t1,
            "tiles": float(len(self._tiles)),
            "tiles_refit": float(sum(f.mesh is None for f in self._tiles.values())),
            "settled": float(ts.settled.sum()),
        }
        return self.summary_

    def settle(self, ts: TrainingSet, post: np.ndarray, t_last_ns: int) -> None:
        """Step 5: events trusted (``settle_p_false``), corroborated by the rest of the data
        (``settle_evidence_nats``) and older than ``settle_after_s`` are settled: from the
        next fit on their rows are pooled and their fate is frozen."""
        ms = self.mapping
        if ms.settle_p_false <= 0:
            return
        old = ts.t_end_ns <= t_last_ns - int(ms.settle_after_s * 1e9)
        prior = np.clip(ts.groups.prior_false, 1e-6, 1 - 1e-6)
        p = np.clip(post, 1e-12, 1 - 1e-12)
        moved = (np.log(p) - np.log1p(-p)) - (np.log(prior) - np.log1p(-prior))
        ok = (post <= ms.settle_p_false) & (moved <= -ms.settle_evidence_nats)
        for g in np.flatnonzero(old & ok & ~ts.settled):
            self._settled.add(ts.keys[int(g)])

    def _check(self) -> None:
        if self.fit_ is None:
            raise NotFittedError("this SurfaceModel is not fitted yet", hint="call fit first")

    # ------------------------------------------------------------------ results

    @property
    def lengthscale_(self) -> float:
        self._check()
        return self._theta[0]

    @property
    def signal_var_(self) -> float:
        self._check()
        return self._theta[1]

    @property
    def weights_(self) -> np.ndarray:
        """Row precisions of the final decisions (1/s^2 if true, excluded if false)."""
        ts = self.training_set_
        rg = ts.groups.row_group
        w = 1.0 / ts.noise_var
        false = (rg >= 0) & self.decided_false_[np.maximum(rg, 0)]
        return np.where(false, 1.0 / (1e4 * self.mapping.outlier_var), w)

    def event_posteriors(self) -> dict[int, float]:
        """Posterior P(false) of every detector event (id -> probability)."""
        self._check()
        ts = self.training_set_
        return {
            int(e): float(p)
            for e, p in zip(ts.event_ids, self.posterior_false_, strict=True)
            if e >= 0
        }

    def flagged_events(self) -> tuple[int, ...]:
        """Detector events decided false (each above its own line), sorted."""
        self._check()
        ts = self.training_set_
        return tuple(sorted(int(e) for e in ts.event_ids[self.decided_false_] if e >= 0))

    def awaiting_events(self) -> tuple[int, ...]:
        """Detector events decided false only for want of corroboration, sorted: their
        posterior is at most ``decide_p`` (an event beside them would keep them) but above
        the lone line. The pilot can settle them by touching the surface there again."""
        self._check()
        ts = self.training_set_
        only_lone = self.decided_false_ & (self.posterior_false_ <= self.decide_p)
        return tuple(sorted(int(e) for e in ts.event_ids[only_lone] if e >= 0))

    def by_observation(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(ids, u, p_false, false)`` of every observation that is a row or a group member:
        ``u = 1 / w_i`` (the effective noise variance of its row, label units^2; NaN for
        members without a row), its event's posterior P(false) (0 for free space) and whether
        its event is decided false."""
        self._check()
        ts = self.training_set_
        post = self.posterior_false_
        false = self.decided_false_
        w = self.weights_
        u_by, p_by, f_by = {}, {}, {}
        for r, members in enumerate(ts.row_members):
            g = int(ts.groups.row_group[r])
            for i in members.tolist():
                u_by[i] = 1.0 / float(w[r])
                p_by[i] = float(post[g]) if g >= 0 else 0.0
                f_by[i] = bool(false[g]) if g >= 0 else False
        for g, members in enumerate(ts.group_ids):
            for i in members.tolist():
                p_by[i] = float(post[g])
                f_by[i] = bool(false[g])
        ids = np.asarray(sorted(p_by), dtype=np.int64)
        u = np.asarray([u_by.get(i, math.nan) for i in ids.tolist()], dtype=np.float64)
        pf = np.asarray([p_by[i] for i in ids.tolist()], dtype=np.float64)
        ff = np.asarray([f_by[i] for i in ids.tolist()], dtype=bool)
        return ids, u, pf, ff

    def predict(self, Xq: np.ndarray, return_std: bool = False):
        """Posterior mean (and latent std) at ``Xq`` (m, d), metres, from each point's tile
        (the prior where no tile was fitted), plus the open-space offset
        (``mapping.open_offset``): the field whose zero set the mesh draws."""
        self._check()
        Xq = np.asarray(Xq, dtype=np.float64)
        offset = self.offset_(Xq)
        mean = self.mapping.prior_mean + offset
        std = np.full(Xq.shape[0], math.sqrt(self.signal_var_))
        keys = self._layout.keys(Xq)
        with blas_threads(self.mapping.blas_threads):
            for key, tile in self._tiles.items():
                sel = np.flatnonzero(np.all(keys == np.asarray(key), axis=1))
                if sel.size == 0:
                    continue
                out = tile.est.predict(Xq[sel], return_std=return_std)
                if return_std:
                    mean[sel], std[sel] = out
                else:
                    mean[sel] = out
                mean[sel] += offset[sel]
        return (mean, std) if return_std else mean

    # ------------------------------------------------------------------ region, field, mesh

    def region(self) -> Region:
        """The data's box plus ``region_margin``, clipped by a configured region."""
        self._check()
        ss = self.surface
        X = self.training_set_.X
        d = X.shape[1]
        data_lo = X.min(axis=0) - ss.region_margin
        data_hi = X.max(axis=0) + ss.region_margin
        lo, hi = data_lo.copy(), data_hi.copy()
        clipped = False
        if len(ss.region_min) == d and len(ss.region_max) == d:
            clo, chi = np.asarray(ss.region_min, float), np.asarray(ss.region_max, float)
            clipped = bool(np.any(clo > data_lo) or np.any(chi < data_hi))
            lo, hi = np.maximum(lo, clo), np.minimum(hi, chi)
        return Region(lo, hi, data_lo, data_hi, clipped)

    def spacing_m(self) -> float:
        """Mesh grid spacing: ``max(spacing, l / voxels_per_lengthscale)``."""
        ss = self.surface
        return max(ss.spacing, self.lengthscale_ / ss.voxels_per_lengthscale)

    def reach_m(self) -> float:
        """How far from an anchor (:meth:`anchors`) the surface may be drawn: 2.5 length scales
        (beyond, the field is the prior and its zero set is noise). A lone touch's plane points
        are anchors themselves, so the reach carries on from them and is not widened again."""
        return REACH_LENGTHSCALES * self.lengthscale_

    def anchors(self, rows: np.ndarray | None = None) -> np.ndarray:
        """(k, d) contact, internal and plane-point rows of the events decided true: where
        surface can be."""
        ts = self.training_set_
        value = np.einsum("ij,ij->i", ts.directions, ts.directions) == 0.0
        sel = self._trusted_rows() & value & (ts.y <= 0.0)  # free space (y > 0) is not
        if rows is not None:
            mask = np.zeros(len(ts), dtype=bool)
            mask[rows] = True
            sel &= mask
        return ts.X[sel]

    def _trusted_rows(self) -> np.ndarray:
        """(n,) bool: the rows of events decided true, and the rows of no event (free space,
        the settled pool)."""
        g = self.training_set_.groups.row_group
        trusted = np.ones(g.size, dtype=bool)
        trusted[g >= 0] = ~self.decided_false_[g[g >= 0]]
        return trusted

    def _clip(self) -> tuple[np.ndarray, np.ndarray]:
        """The configured region clip (infinite when none)."""
        ss = self.surface
        if len(ss.region_min) == 3 and len(ss.region_max) == 3:
            return np.asarray(ss.region_min, float), np.asarray(ss.region_max, float)
        return np.full(3, -np.inf), np.full(3, np.inf)

    def _tile_grid(self, key: tuple, s: float) -> Grid | None:
        """The tile's core on the global lattice of spacing ``s``, within the configured clip
        (the data's box needs no cut: nothing is evaluated beyond reach of its contacts).

        A tile's grid runs from the first lattice plane in its core to the first plane of the
        next tile, so neighbours share that plane: every cell of the lattice is meshed by
        exactly one tile, also when ``s`` does not divide the tile edge (otherwise a face lying
        between the two tiles' last planes, such as a wall on a tile boundary, is lost)."""
        lo, hi = self._layout.core(key)
        clo, chi = self._clip()
        i0 = np.ceil(np.maximum(lo, clo) / s - 1e-9)
        i1 = np.minimum(np.ceil(hi / s - 1e-9), np.floor(chi / s + 1e-9))
        if np.any(i1 - i0 < 1):
            return None
        return Grid.from_bounds(i0 * s, i1 * s, s)

    def _tile_mesh(self, tile: _TileFit, s: float) -> SurfaceMesh:
        from scipy.spatial import cKDTree

        grid = self._tile_grid(tile.key, s)
        pts = self.anchors(tile.rows)
        if grid is None or pts.shape[0] == 0:
            return SurfaceMesh.empty(with_std=True)
        tree, r = cKDTree(pts), self.reach_m()

        def active(q: np.ndarray) -> np.ndarray:
            d, _ = tree.query(q, distance_upper_bound=r)
            return np.isfinite(d)

        clock = self._mesh_clock

        def field(q: np.ndarray) -> np.ndarray:
            t0 = time.perf_counter()
            mean = tile.est.predict(q)
            t1 = time.perf_counter()
            offset = self.offset_(q)
            clock["mesh_gp_s"] += t1 - t0
            clock["mesh_offset_s"] += time.perf_counter() - t1
            return mean + offset

        band = narrow_band_field(
            field, grid, coarse_factor=self.surface.coarse_factor,
            band_voxels=self.surface.band_voxels, active=active,
        )  # fmt: skip
        mesh = extract_surface(band.values, band.grid)
        if mesh.is_empty:
            return SurfaceMesh.empty(with_std=True)
        d, _ = tree.query(mesh.vertices)  # faces of the inactive fill's edge are not surface
        mesh = _faces_subset(mesh, (d[mesh.faces] <= r - 2.0 * s).all(axis=1))
        if mesh.is_empty:
            return SurfaceMesh.empty(with_std=True)
        _, std = tile.est.predict(mesh.vertices, return_std=True)
        mesh = SurfaceMesh(mesh.vertices, mesh.faces, mesh.normals, std)
        frac = self.surface.max_std_fraction
        if frac < 1.0:
            mesh = confident_part(mesh, frac * math.sqrt(self.signal_var_))
        return mesh

    def mesh(self, with_std: bool = True) -> SurfaceMesh:
        """Zero-level mesh with the predictive std at its vertices, confident faces only:
        the union of the tiles' meshes (a tile whose fit did not change keeps its mesh), welded
        where neighbours meet (``surface.weld_lattice``: one surface, not one per tile)."""
        self._check()
        if self.training_set_.X.shape[1] != 3:
            raise InputDataError("mesh() needs 3D data; use predict on a 2D grid instead")
        t0 = time.perf_counter()
        self._mesh_clock = {"mesh_gp_s": 0.0, "mesh_offset_s": 0.0}
        s = self.spacing_m()
        with blas_threads(self.mapping.blas_threads):
            for tile in self._tiles.values():
                # the offset near the tile is part of what its mesh was drawn from (its free
                # samples only through the tile's rows: a new one within the halo refits it)
                key = (s, signature(self.offset_.digest_near(*self._layout.core(tile.key))))
                if tile.mesh is None or tile.mesh_key != key:
                    tile.mesh = self._tile_mesh(tile, s)
                    tile.mesh_key = key
        parts = [t.mesh for t in self._tiles.values() if not t.mesh.is_empty]
        mesh = weld_lattice(_concatenate(parts), s)  # neighbours share their boundary plane
        if self.surface.drop_cavities and not mesh.is_empty:
            mesh = _faces_subset(mesh, ~self._cavities(mesh))
        self.timings_.update(mesh_s=time.perf_counter() - t0, **self._mesh_clock)
        return mesh

    def _cavities(self, mesh: SurfaceMesh) -> np.ndarray:
        """Faces of ``mesh`` in a cavity (``mapping/cavities.py``), seen from the trusted
        contacts (their rows, pooled ones included, and normals) and the free-space rows."""
        ts = self.training_set_
        facing = np.einsum("ij,ij->i", ts.normals, ts.normals) > 0.0  # contact rows, not slopes
        touch = self._trusted_rows() & (ts.y == 0.0) & facing
        return cavity_faces(
            mesh, ts.X[touch], ts.normals[touch], ts.X[ts.y > 0.0],
            depth_m=CAVITY_DEPTH_INTERNALS * self.policy.internal_depth_m,
        )  # fmt: skip


@dataclasses.dataclass
class _TileFit:
    """One tile's fit: its rows (global indices), groups, input digest, estimator, mesh."""

    key: tuple
    rows: np.ndarray
    gidx: np.ndarray
    signature: str
    est: EventMixtureGPIS
    mesh: SurfaceMesh | None
    mesh_key: tuple | None = None  # (grid spacing, digest of the open-space offset near it)

    def __post_init__(self) -> None:
        self.local = {int(g): k for k, g in enumerate(self.gidx.tolist())}


def _concatenate(parts: list[SurfaceMesh]) -> SurfaceMesh:
    if not parts:
        return SurfaceMesh.empty(with_std=True)
    if len(parts) == 1:
        return parts[0]
    offs = np.cumsum([0] + [p.vertices.shape[0] for p in parts[:-1]])
    return SurfaceMesh(
        np.concatenate([p.vertices for p in parts]),
        np.concatenate([p.faces + o for p, o in zip(parts, offs, strict=True)]),
        np.concatenate([p.normals for p in parts]),
        np.concatenate([p.std for p in parts]),
    )


def _faces_subset(mesh: SurfaceMesh, keep: np.ndarray) -> SurfaceMesh:
    """The mesh with only the faces ``keep`` (unused vertices dropped)."""
    if keep.all():
        return mesh
    faces = mesh.faces[keep]
    used = np.unique(faces)
    remap = np.full(mesh.vertices.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    std = None if mesh.std is None else mesh.std[used]
    return SurfaceMesh(mesh.vertices[used], remap[faces], mesh.normals[used], std)
