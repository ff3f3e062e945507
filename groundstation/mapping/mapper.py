"""The mapper core (pure): training set, data-clock refit schedule, warm refits, flags, mesh.

:class:`Mapper` keeps every observation it was given (by id; a repeated id is ignored), decides
from the *data* clock when a refit is due, refits the default surface model
(:class:`~groundstation.mapping.model.SurfaceModel`: merge, exact/sparse robust GPIS warm-started
from the previous fit, narrow-band mesh) on everything received so far, checks the fit
(:func:`~groundstation.mapping.diagnostics.diagnose`) and returns a :class:`FitResult`. The mapper
process (``runtime/workers/mapper.py``) and the offline pipeline run this same object.

Schedule (:meth:`Mapper.due`)
-----------------------------
A refit is due when at least ``min_contacts`` contact observations and one external one are
held, something new arrived since the last fit, and either ``refit_min_new`` new observations
arrived, or the data time advanced ``refit_period_s`` past the data time of the last fit (for
the first fit: past the first observation), or (``refit_on_contact``) a new contact arrived
with its internal point: a touch reaches the mesh one refit after the detector publishes it,
not after up to a whole period (the 10-minute live soak measured contact-to-mesh p95 3.2 s with
the period alone). Time is the observations' ``t_ns`` (station axis),
never the wall clock, so a replay at any speed refits at the same data times. A refit always
uses *all* observations held when it starts: if the process falls behind, the next refit
simply covers more data (skip ahead) and the lag is ``data_ns - FitResult.data_ns``.

False-positive flags (rule on u_i)
----------------------------------
Only contacts (y = 0) can be false (ALGORITHM.md §7.5). A contact observation is *suspect* when

    u_i > beta / (alpha + 1/2) + flag_u

i.e. when its u exceeds by ``flag_u`` the value u takes for a datum the fit explains exactly
(E3/E4 with s_i = 0; ~beta at its floor, 1e-6, in a heavy-tailed fit). A fit on the Gaussian
plateau (alpha >= 1e4, ALGORITHM.md §7.3) gives every datum the same u: it flags nothing. (An
earlier rule also asked for u_i > 3 x the median contact u; in a gusty session where false
contacts are the majority of contacts it flagged nothing at all.) A contact *event* is flagged
when at least ``flag_event_fraction`` of its contact observations are suspect; then every contact
and internal observation of that event carries flag bit 0. A suspect contact of an unflagged
event is flagged with its paired internal point (same event, same time). External points are
never flagged. ``flag_u`` = 0.3 is measured on 11 SITL sessions (``replay_logs/`` and 8 more
seeds): true touches stay below it, false contacts refuted by the flown path reach 0.5-0.7.

Failure handling
----------------
An exception in the fit, or a fit :func:`diagnose` finds unreliable (``not_converged`` is not
counted for warm refits, which are capped at ``mapping.refit_max_iter`` by design), keeps the
last good mesh and flags, marks the result ``reliable=False`` with the reasons, and tries the
documented fallback once (``diagnostics.FALLBACKS``): ``fixed_theta`` refits a fresh model from
the last good hyperparameters with ``optimize=False``; ``gpis_init`` refits a fresh model cold
from the paper's initial values. A reliable fallback fit replaces the model for later refits.

Restart: :meth:`Mapper.restore` rebuilds the training set from the observations seen so far
(from the recording of the ``observations`` topic); nothing is lost.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterable

import numpy as np

from groundstation.contact.detector import Observation
from groundstation.contact.vehicle import VehicleSettings
from groundstation.errors import GroundstationError
from groundstation.mapping.diagnostics import diagnose
from groundstation.mapping.model import SurfaceModel
from groundstation.mapping.robust import PLATEAU_ALPHA  # the Gaussian plateau (§7.3)
from groundstation.mapping.settings import MapperSettings, MappingSettings, SurfaceSettings
from groundstation.mapping.surface import SurfaceMesh

FLAG_FALSE_POSITIVE = 1  # mapper.fit flag bit 0
FLAG_AWAITING = 2  # bit 1: flagged only for want of a second touch near it (with bit 0)
#: The parts of a refit's time a :class:`FitResult` reports (``timings``), seconds.
REFIT_STAGES = ("rows_s", "fit_s", "mesh_s", "mesh_gp_s", "mesh_offset_s", "total_s")


@dataclasses.dataclass
class FitResult:
    """One refit.

    Attributes
    ----------
    fit_index : int
        0, 1, ... per refit attempt.
    data_ns : int
        Data time of the newest observation in the fit (station axis, ns).
    ids, u : (n,) int64, float64
        Every observation id held and its u_i (members of a merged cell share its u).
    flags : (n,) uint8
        Flag bits (bit 0: flagged false-positive contact; bit 1, with bit 0: its event is
        flagged only because nothing corroborates it, see ``awaiting_events``).
    flagged_events : tuple of int
        Contact event ids flagged as false positives.
    mesh : SurfaceMesh or None
        This fit's mesh, or the last good one when this fit is unreliable (None before any).
    mesh_fit_index : int
        Fit index the mesh belongs to (-1 when there is none).
    timings : dict
        Seconds (wall clock, for reports only): ``total_s``; of it ``rows_s`` (observations to
        rows), ``fit_s`` (the tiles' fits), ``mesh_s`` (the mesh) and, of the mesh,
        ``mesh_gp_s`` (GP means) and ``mesh_offset_s`` (open-space offset); the map engine v2's
        refits carry every key, the legacy engine's a subset (:data:`REFIT_STAGES`).
    hyperparameters : dict
        lengthscale, signal_var, alpha, beta, mode, n_train.
    reliable : bool
    reasons : tuple of str
        Why not reliable (diagnostics reason strings, or ``fit_error: ...``).
    fallback : str
        Fallback tried ("none" if none).
    p_false : (n,) float64 or None
        Posterior probability that each observation's event is false (mixture engine; 0 for
        free space, NaN unknown; None for the legacy engine).
    notes : tuple of str
        Facts worth showing that do not make the fit unreliable (``region_clipped``).
    awaiting_events : tuple of int
        The flagged events the map would keep if a second touch corroborated them (decided
        false on ``mapper.lone_flag_p`` with a posterior at most ``mapper.flag_p``): where the
        pilot should touch again.
    """

    fit_index: int
    data_ns: int
    ids: np.ndarray
    u: np.ndarray
    flags: np.ndarray
    flagged_events: tuple[int, ...]
    mesh: SurfaceMesh | None
    mesh_fit_index: int
    timings: dict
    hyperparameters: dict
    reliable: bool
    reasons: tuple[str, ...]
    fallback: str = "none"
    p_false: np.ndarray | None = None
    notes: tuple[str, ...] = ()
    awaiting_events: tuple[int, ...] = ()


def default_model_factory(mapping: MappingSettings, surface: SurfaceSettings):
    """The legacy engine's surface model (``mapping.engine = legacy``)."""
    from groundstation.mapping.legacy import LegacySurfaceModel

    return LegacySurfaceModel(mapping, surface)


class Mapper:
    """Training set + schedule + refits (see the module docstring).

    Parameters
    ----------
    settings : MapperSettings
    mapping : MappingSettings
    surface : SurfaceSettings
    model_factory : callable, optional
        Legacy engine only: ``(mapping, surface) -> model`` with ``fit(X, y, ids, t_ns)``,
        ``mesh()``, ``uncertainty_by_id()``, ``timings_``, ``mode_``, ``fit_``.
    vehicle : VehicleSettings, optional
        The body whose swept volume refutes contacts (mixture engine).
    internal_depth_m : float
        The detector's d_in (mixture engine).
    """

    def __init__(
        self,
        settings: MapperSettings | None = None,
        mapping: MappingSettings | None = None,
        surface: SurfaceSettings | None = None,
        model_factory: Callable | None = None,
        vehicle: VehicleSettings | None = None,
        internal_depth_m: float = 0.1,
    ) -> None:
        self.settings = settings or MapperSettings()
        self.mapping = mapping or MappingSettings()
        self.surface = surface or SurfaceSettings()
        self._factory = model_factory or default_model_factory
        if self.mapping.engine == "mixture" and model_factory is None:
            self._model = SurfaceModel(
                self.mapping, self.surface, vehicle, internal_depth_m,
                decide_p=self.settings.flag_p, lone_decide_p=self.settings.lone_flag_p,
            )  # fmt: skip
        else:
            self._model = self._factory(self.mapping, self.surface)
        self._obs: dict[int, Observation] = {}
        self._new = 0
        self._new_contacts = 0  # contact / internal observations since the last refit
        self._new_inside = 0
        self._n_contacts = 0
        self._n_external = 0
        self.data_ns: int | None = None  # newest observation time held
        self._first_ns: int | None = None
        self._last_fit_ns: int | None = None
        self.fit_index = -1
        self.duplicates = 0
        self.last_good: FitResult | None = None
        self._last_good_theta: dict[str, float] | None = None

    # -- training set --------------------------------------------------------------------------
    def add(self, observations: Iterable[Observation]) -> int:
        """Add observations (any order); a repeated id is ignored. Returns how many were new."""
        n = 0
        for o in observations:
            if o.id in self._obs:
                self.duplicates += 1
                continue
            self._obs[o.id] = o
            n += 1
            if o.label == 0:
                self._n_contacts += 1
                self._new_contacts += 1
            elif o.label < 0:
                self._new_inside += 1
            elif o.label > 0:
                self._n_external += 1
            t = int(o.t_ns)
            self.data_ns = t if self.data_ns is None else max(self.data_ns, t)
            self._first_ns = t if self._first_ns is None else min(self._first_ns, t)
        self._new += n
        return n

    @classmethod
    def from_config(cls, config) -> Mapper:
        """The mapper of a station :class:`~groundstation.config.Config` (its ``mapper``,
        ``mapping``, ``surface`` and ``vehicle`` sections and the detector's ``d_in``)."""
        return cls(
            config.mapper,
            config.mapping,
            config.surface,
            vehicle=config.vehicle,
            internal_depth_m=config.contact.internal_depth_m,
        )

    @classmethod
    def restore(cls, observations: Iterable[Observation], *args, **kwargs) -> Mapper:
        """A mapper rebuilt from the observations seen before a restart (no refit yet)."""
        m = cls(*args, **kwargs)
        m.add(observations)
        return m

    def __len__(self) -> int:
        return len(self._obs)

    @property
    def pending(self) -> int:
        """Observations received since the last refit."""
        return self._new

    def observations(self) -> list[Observation]:
        """Every observation held, by id."""
        return [self._obs[k] for k in sorted(self._obs)]

    # -- schedule ------------------------------------------------------------------------------
    def due(self, t_ns: int | None = None) -> bool:
        """Whether a refit is due at data time ``t_ns`` (default: the newest observation's)."""
        s = self.settings
        if self._new == 0 or self._n_contacts < s.min_contacts or self._n_external < 1:
            return False
        if self._new >= s.refit_min_new:
            return True
        if s.refit_on_contact and 0 < self._new_contacts <= self._new_inside:
            return True
        t = self.data_ns if t_ns is None else int(t_ns)
        ref = self._last_fit_ns if self._last_fit_ns is not None else self._first_ns
        return t - ref >= int(s.refit_period_s * 1e9)

    def ready(self) -> bool:
        """Enough data for a fit (used for the final refit at the end of a replay)."""
        s = self.settings
        return self._n_contacts >= s.min_contacts and self._n_external >= 1

    # -- refit ---------------------------------------------------------------------------------
    def refit(self, learn_kernel: bool = False) -> FitResult:
        """Refit on every observation held (see the module docstring). Never raises for a
        failed fit: the result is then ``reliable=False`` and keeps the last good mesh.
        ``learn_kernel``: the map engine v2 learns its kernel at this fit even if the data
        have not grown enough since it last did (a final map's last fit)."""
        obs = self.observations()
        self.fit_index += 1
        self._new = self._new_contacts = self._new_inside = 0
        data_ns = max(o.t_ns for o in obs) if obs else 0
        self._last_fit_ns = data_ns
        if isinstance(self._model, SurfaceModel):
            return self._refit_mixture(obs, data_ns, learn_kernel)
        ids = np.array([o.id for o in obs], dtype=np.int64)
        X = np.array([o.position for o in obs], dtype=np.float64).reshape(-1, 3)
        y = np.array([o.label for o in obs], dtype=np.float64)
        t_ns = np.array([o.t_ns for o in obs], dtype=np.int64)
        t0 = time.perf_counter()
        result = self._attempt(self._model, X, y, ids, t_ns, warm=self.fit_index > 0)
        fallback = "none"
        if not result[0] and self.settings.fallback and result[3] is not None:
            fallback = result[3]
            alt = self._fallback_model(fallback)
            if alt is not None:
                alt_result = self._attempt(alt, X, y, ids, t_ns, warm=False)
                if alt_result[0]:
                    self._model, result = alt, alt_result
        ok, reasons, mesh, _, hyper, timings = result
        timings["total_s"] = time.perf_counter() - t0
        if ok:
            u_ids, u = self._model.uncertainty_by_id()
            u_by_id = dict(
                zip(u_ids.tolist(), np.asarray(u, dtype=np.float64).tolist(), strict=True)
            )
            u_arr = np.array([u_by_id.get(i, np.nan) for i in ids.tolist()], dtype=np.float64)
            flags, events = flag_observations(obs, u_arr, self.settings, **_noise_floor(hyper))
            res = FitResult(
                self.fit_index, data_ns, ids, u_arr, flags, events, mesh, self.fit_index,
                timings, hyper, True, (), fallback,
            )  # fmt: skip
            self.last_good = res
            self._last_good_theta = {
                k: hyper[k] for k in ("lengthscale", "signal_var", "alpha", "beta") if k in hyper
            }
            return res
        # unreliable: keep the last good mesh and per-id values (new ids: u nan -> 0, no flag)
        lg = self.last_good
        u_arr = np.zeros(len(ids))
        flags = np.zeros(len(ids), dtype=np.uint8)
        events: tuple[int, ...] = ()
        if lg is not None:
            pos = {i: k for k, i in enumerate(lg.ids.tolist())}
            for k, i in enumerate(ids.tolist()):
                if i in pos:
                    u_arr[k] = lg.u[pos[i]]
                    flags[k] = lg.flags[pos[i]]
            events = lg.flagged_events
        return FitResult(
            self.fit_index, data_ns, ids, u_arr, flags, events,
            None if lg is None else lg.mesh, -1 if lg is None else lg.mesh_fit_index,
            timings, hyper, False, reasons, fallback,
        )  # fmt: skip

    def _refit_mixture(
        self, obs: list[Observation], data_ns: int, learn_kernel: bool = False
    ) -> FitResult:
        """A refit of the mixture engine: fit, mesh, flags by posterior per event."""
        s, model = self.settings, self._model
        ids = np.array([o.id for o in obs], dtype=np.int64)
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        try:
            summary = model.fit(obs, learn_kernel=learn_kernel)
            mesh = None
            if s.with_mesh:
                t1 = time.perf_counter()
                mesh = model.mesh()
                timings["mesh_s"] = time.perf_counter() - t1
            region = model.region()
        except (GroundstationError, ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
            timings["fit_s"] = time.perf_counter() - t0
            timings["total_s"] = timings["fit_s"]
            return self._unreliable(ids, data_ns, timings, {}, (f"fit_error: {exc}",), "none")
        timings.update(
            fit_s=model.timings_.get("fit_s", 0.0), rows_s=model.timings_.get("rows_s", 0.0)
        )
        timings.update(
            {k: v for k, v in model.timings_.items() if k in ("mesh_gp_s", "mesh_offset_s")}
        )
        timings["total_s"] = time.perf_counter() - t0
        oid, u, pf, false = model.by_observation()
        u_by = dict(zip(oid.tolist(), u.tolist(), strict=True))
        p_by = dict(zip(oid.tolist(), pf.tolist(), strict=True))
        f_by = dict(zip(oid.tolist(), false.tolist(), strict=True))
        u_arr = np.array([u_by.get(i, math.nan) for i in ids.tolist()], dtype=np.float64)
        p_arr = np.array([p_by.get(i, math.nan) for i in ids.tolist()], dtype=np.float64)
        f_arr = np.array([f_by.get(i, False) for i in ids.tolist()], dtype=bool)
        flags = np.where(f_arr, FLAG_FALSE_POSITIVE, 0).astype(np.uint8)
        flagged = model.flagged_events()
        awaiting = model.awaiting_events()
        event_of = np.array([o.event_id for o in obs], dtype=np.int64)
        flags[f_arr & np.isin(event_of, awaiting)] |= FLAG_AWAITING
        hyper = {
            "lengthscale": summary.lengthscale,
            "signal_var": summary.signal_var,
            "log_marginal": summary.log_marginal,
            "n_iter": summary.n_iter,
            "n_train": summary.n_train,
            "n_groups": summary.n_groups,
            "mode": "mixture",
            "kernel_held": summary.kernel_held,
            "region_min": region.lo.tolist(),
            "region_max": region.hi.tolist(),
        }
        finite = np.isfinite(model.fit_.posterior_false_).all() and math.isfinite(
            summary.log_marginal
        )
        reasons = () if finite else ("nonfinite_output",)
        notes = ("region_clipped",) if region.clipped else ()
        if reasons:
            return self._unreliable(ids, data_ns, timings, hyper, reasons, "none")
        res = FitResult(
            self.fit_index, data_ns, ids, u_arr, flags, flagged, mesh, self.fit_index,
            timings, hyper, True, (), "none", p_arr, notes, awaiting,
        )  # fmt: skip
        self.last_good = res
        return res

    def _unreliable(self, ids, data_ns, timings, hyper, reasons, fallback) -> FitResult:
        """Keep the last good mesh and per-id values (new ids: u nan -> 0, no flag)."""
        lg = self.last_good
        u_arr = np.zeros(len(ids))
        p_arr = np.full(len(ids), np.nan)
        flags = np.zeros(len(ids), dtype=np.uint8)
        events: tuple[int, ...] = ()
        if lg is not None:
            pos = {i: k for k, i in enumerate(lg.ids.tolist())}
            for k, i in enumerate(ids.tolist()):
                if i in pos:
                    u_arr[k] = lg.u[pos[i]]
                    flags[k] = lg.flags[pos[i]]
                    if lg.p_false is not None:
                        p_arr[k] = lg.p_false[pos[i]]
            events = lg.flagged_events
        return FitResult(
            self.fit_index, data_ns, ids, u_arr, flags, events,
            None if lg is None else lg.mesh, -1 if lg is None else lg.mesh_fit_index,
            timings, hyper, False, tuple(reasons), fallback, p_arr,
            awaiting_events=() if lg is None else lg.awaiting_events,
        )  # fmt: skip

    def _attempt(self, model, X, y, ids, t_ns, warm: bool):
        """(ok, reasons, mesh, fallback key, hyperparameters, timings) of one fit."""
        s = self.settings
        timings: dict[str, float] = {}
        hyper: dict = {}
        t0 = time.perf_counter()
        try:
            model.fit(X, y, ids, t_ns)
            timings["fit_s"] = time.perf_counter() - t0
            hyper = _hyperparameters(model)
            mesh = None
            if s.with_mesh:
                t1 = time.perf_counter()
                mesh = model.mesh()
                timings["mesh_s"] = time.perf_counter() - t1
            diag = diagnose(
                model,
                flag_fraction_max=1.0,  # our own relative rule is checked below
                flag_u=s.flag_u,
                outliers_expected=s.expect_outliers,
                surface=mesh,
                have_last_good=self._last_good_theta is not None,
                constraints=_constraints(self.mapping),
            )
        except (GroundstationError, ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
            timings.setdefault("fit_s", time.perf_counter() - t0)
            return False, (f"fit_error: {exc}",), None, "gpis_init", hyper, timings
        skip = {"too_many_flagged"} | ({"not_converged"} if warm else set())
        reasons = [r for r in diag.reasons if r not in skip]
        u_ids, u = model.uncertainty_by_id()
        labels = {o_id: lab for o_id, lab in zip(ids.tolist(), y.tolist(), strict=True)}
        uc = np.array([v for i, v in zip(u_ids.tolist(), u, strict=True) if labels.get(i) == 0])
        floor = _noise_floor(hyper)
        if uc.size and np.all(np.isfinite(uc)) and not floor["plateau"]:
            if float(np.mean(uc > floor["u_floor"] + s.flag_u)) > s.flag_fraction_max:
                reasons.append("too_many_flagged")
        reasons = tuple(reasons)
        if not reasons:
            return True, (), mesh, None, hyper, timings
        return False, reasons, None, diag.fallback, hyper, timings

    def _fallback_model(self, key: str):
        if key == "fixed_theta" and self._last_good_theta:
            th = self._last_good_theta
            mapping = dataclasses.replace(
                self.mapping,
                optimize=False,
                **{k: float(v) for k, v in th.items() if k in ("lengthscale", "signal_var")},
                **{k: float(v) for k, v in th.items() if k in ("alpha", "beta") and v > 0},
            )
            return self._factory(mapping, self.surface)
        if key == "gpis_init":
            return self._factory(self.mapping, self.surface)  # fresh, cold: paper's initial values
        return None


def _constraints(mapping: MappingSettings) -> tuple[str, ...]:
    """Configured kernel bounds that act as modelling constraints (``diagnose``): the length
    scale floor (map resolution) and the signal variance cap, when set inside the estimators'
    own search bounds (1e-2 m, 1e3)."""
    out = []
    if mapping.lengthscale_min > 1e-2:
        out.append("lengthscale_lower")
    if mapping.signal_var_max < 1e3:
        out.append("signal_var_upper")
    return tuple(out)


def _hyperparameters(model) -> dict:
    est = getattr(model, "fit_", model)
    out: dict = {}
    for name in ("lengthscale", "signal_var", "alpha", "beta", "noise_var"):
        v = getattr(est, name + "_", None)
        if v is not None and np.isfinite(v):
            out[name] = float(v)
    out["mode"] = str(getattr(model, "mode_", "exact"))
    n = getattr(model, "n_train_", None)
    if n is not None:
        out["n_train"] = int(n)
    return out


def _noise_floor(hyper: dict) -> dict:
    """``u_floor`` = beta / (alpha + 1/2) and ``plateau`` of a fit's hyperparameters (a GPIS
    fit has neither: floor 0, no plateau)."""
    alpha, beta = hyper.get("alpha"), hyper.get("beta")
    if alpha is None or beta is None:
        return {"u_floor": 0.0, "plateau": False}
    return {"u_floor": float(beta) / (float(alpha) + 0.5), "plateau": alpha >= PLATEAU_ALPHA}


def flag_observations(
    obs: list[Observation],
    u: np.ndarray,
    settings: MapperSettings,
    u_floor: float = 0.0,
    plateau: bool = False,
) -> tuple[np.ndarray, tuple[int, ...]]:
    """Flag bits per observation and the flagged event ids (rule in the module docstring).

    Parameters
    ----------
    obs : list of Observation, length n
    u : (n,) float64
        u_i of each observation (NaN: unknown, never suspect).
    settings : MapperSettings
    u_floor : float
        The fit's beta / (alpha + 1/2) (label units^2).
    plateau : bool
        The fit sits on the Gaussian plateau: nothing is flagged.

    Returns
    -------
    flags : (n,) uint8
    events : tuple of int, sorted
    """
    u = np.asarray(u, dtype=np.float64)
    labels = np.array([o.label for o in obs], dtype=np.float64)
    contact = labels == 0
    flags = np.zeros(len(obs), dtype=np.uint8)
    if not np.any(contact) or plateau:
        return flags, ()
    with np.errstate(invalid="ignore"):
        suspect = contact & np.isfinite(u) & (u > u_floor + settings.flag_u)
    per_event: dict[int, list[bool]] = {}
    for k, o in enumerate(obs):
        if contact[k] and o.event_id >= 0:
            per_event.setdefault(o.event_id, []).append(bool(suspect[k]))
    events = tuple(
        sorted(e for e, s in per_event.items() if np.mean(s) >= settings.flag_event_fraction)
    )
    flagged_events = set(events)
    suspect_keys = {(o.event_id, o.t_ns) for k, o in enumerate(obs) if suspect[k]}
    for k, o in enumerate(obs):
        if o.label > 0:
            continue
        if o.event_id in flagged_events or (o.event_id, o.t_ns) in suspect_keys:
            flags[k] |= FLAG_FALSE_POSITIVE
    return flags, events
