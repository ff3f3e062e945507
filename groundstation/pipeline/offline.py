"""The in-process pipeline over a recording: ``iter_replay`` -> ContactStage -> Mapper.

No sockets, threads or processes: the same pure cores as the detector and mapper processes,
driven by the log. The mapper is asked :meth:`~groundstation.mapping.mapper.Mapper.due` after
every observation (the process asks after every batch it drained, so on the data clock both
refit at the same points unless the process falls behind and skips ahead), and once more at the
end of the data (a final refit on everything, as the mapper process does when the detector
reports the end of a replay).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable, Iterator, Sequence

from groundstation.acquisition.replay import iter_replay
from groundstation.acquisition.segments import open_session as open_recording  # segments as one
from groundstation.bus.envelope import Envelope
from groundstation.config import Config, load_config
from groundstation.contact.detector import Observation
from groundstation.contact.stage import INPUT_TOPICS, ContactStage, observation_from_envelope
from groundstation.mapping.mapper import FitResult, Mapper

Progress = Callable[[float, float, int, int], None]  # (log s done, log s total, refits, contacts)


@dataclasses.dataclass
class PipelineResult:
    """What one pipeline run produced.

    Attributes
    ----------
    log_path : str
    mode : "in-process" | "multi-process"
    events : list of Envelope
        ``contact.event`` messages (begin and end) in order.
    observations : list of Observation
    fits : list of FitResult
        Every refit; meshes are kept only on the last ``keep_meshes`` (older ones: None).
    duration_s : float
        Log time covered by the recording.
    start_ns : int
        Log start time (ns).
    truth : dict or None
    wall_s : float
        Wall time of the run.
    gaps : dict
        Sequence gaps per topic seen by the pipeline's subscribers (multi-process; {} else).
    stats : dict
        Stage / process counters.
    """

    log_path: str
    mode: str
    events: list[Envelope]
    observations: list[Observation]
    fits: list[FitResult]
    duration_s: float
    start_ns: int
    truth: dict | None
    wall_s: float = 0.0
    gaps: dict = dataclasses.field(default_factory=dict)
    stats: dict = dataclasses.field(default_factory=dict)

    @property
    def final(self) -> FitResult | None:
        """The last refit (its mesh is the last good one)."""
        return self.fits[-1] if self.fits else None

    @property
    def contacts(self) -> int:
        """Contact events detected (begin messages)."""
        return sum(e.payload["state"] == "begin" for e in self.events)


def event_key(env: Envelope) -> tuple:
    """What "the same contact event message" means: id, state, data time, peak and the exact
    bytes of position and normal (sequence numbers and receive times left out)."""
    a = env.arrays
    return (
        int(env.payload["id"]),
        env.payload["state"],
        int(env.header.source_ns),
        float(env.payload["peak_g"]),
        a["position_m"].tobytes(),
        a["normal"].tobytes(),
    )


def recording_span(path: str) -> tuple[int, float, dict | None]:
    """(log start ns, duration s, truth document or None) of a recording."""
    with open_recording(path) as rec:
        return int(rec.summary.start_ns or 0), rec.summary.duration_s, rec.truth()


@dataclasses.dataclass
class DetectionRun:
    """The detector stage alone on a recording (what ``bench detector`` measures).

    Attributes
    ----------
    log_path : str
    events : list of Envelope
        ``contact.event`` messages in order (begin/end, and rejected candidates).
    observations : list of Observation
    duration_s : float
    start_ns : int
    truth : dict or None
    stats : dict
        Detector stage counters.
    wall_s : float
    """

    log_path: str
    events: list[Envelope]
    observations: list[Observation]
    duration_s: float
    start_ns: int
    truth: dict | None
    stats: dict
    wall_s: float


def detect_offline(log_path: str, config: Config | None = None) -> DetectionRun:
    """Run only the detector stage on ``log_path`` (the same code as :func:`run_offline`)."""
    cfg = config or load_config()
    t_wall = time.perf_counter()
    start_ns, duration, truth = recording_span(log_path)
    stage = ContactStage(cfg.contact, cfg.alignment, vehicle=cfg.vehicle, batch=64)
    events, observations = _split(_stage_outputs(stage, log_path, cfg, None))
    return DetectionRun(
        str(log_path), events, observations, duration, start_ns, truth,
        stage.stats.as_dict(), time.perf_counter() - t_wall,
    )  # fmt: skip


def _stage_batches(
    stage: ContactStage,
    log_path: str,
    cfg: Config,
    progress: Callable[[int], None] | None,
    start: float | None = None,
    end: float | None = None,
    tap: Callable[[Envelope], None] | None = None,
) -> Iterator[list[Envelope]]:
    """The stage's outputs, one list per input sample that produced any (a contact's pairs
    come out together, as the detector process publishes them)."""
    for env in iter_replay(log_path, start, end, settings=cfg.acquisition):
        if env.topic not in INPUT_TOPICS:
            continue
        if tap is not None:
            tap(env)
        out = stage.push(env)
        if out:
            yield out
        if progress is not None:
            progress(env.header.recv_ns)
    out = stage.flush()
    if out:
        yield out


def _stage_outputs(*args, **kwargs) -> Iterator[Envelope]:
    """:func:`_stage_batches`, flattened."""
    for batch in _stage_batches(*args, **kwargs):
        yield from batch


def _split(outs: Iterable[Envelope]) -> tuple[list[Envelope], list[Observation]]:
    events: list[Envelope] = []
    observations: list[Observation] = []
    for env in outs:
        if env.topic == "contact.event":
            events.append(env)
        else:
            observations.append(observation_from_envelope(env))
    return events, observations


def run_offline(
    log_path: str,
    config: Config | None = None,
    *,
    progress: Progress | None = None,
    keep_meshes: int = 3,
    map_mode: str = "live",
    checkpoints: int | None = None,
    start: float | None = None,
    end: float | None = None,
    tap: Callable[[Envelope], None] | None = None,
    inject: Sequence[Observation] = (),
) -> PipelineResult:
    """Run the whole pipeline in process on ``log_path``.

    Parameters
    ----------
    log_path : str
        MCAP recording (a truncated one is read up to its last complete chunk).
    config : Config, optional
        Defaults when None.
    progress : callable, optional
        Called about every 5 s of log time with (log s done, log s total, refits, contacts).
    keep_meshes : int
        Keep the meshes of this many last fits (for snapshots).
    map_mode : "live" | "final"
        ``live``: refit on the live cadence (``mapper.refit_period_s`` of data time), as a live
        session does. ``final``: detect over the whole log and fit only where the live mapper
        would learn its kernel (``checkpoints``), then once on everything, for when the final
        map is what matters.
    checkpoints : int, optional
        Intermediate fits of ``map_mode = "final"``. None (default): a fit each time the
        observations held have grown by ``mapping.theta_refit_growth`` since the last one, the
        refits at which the live mapper learns its kernel and warm-starts the decisions of the
        next (22 fits on a 40-minute survey, against 1,212 refits live). One cold fit on
        everything learns the kernel with every gust weighted as a touch and lost surface the
        warm-started sequence kept (40-minute survey: missing share 0.68 against 0.42).
        ``N``: N fits at evenly spaced data times instead (0: the final fit alone).
    start, end : float, optional
        Log window, seconds from the log start (``end`` exclusive): ``replay --start/--end``.
    tap : callable, optional
        Called with every decoded sample envelope before the detector sees it (replay outputs
        translate them to Foxglove channels without decoding the log twice).
    inject : sequence of Observation
        Extra observations (ids and event ids unused by the detector) handed to the mapper with
        the first detector output at or after their data time, as if the detector had made
        them (``bench inject`` plants a false contact in a real flight this way). They are in
        ``observations`` of the result.
    """
    if map_mode not in ("live", "final"):
        raise ValueError(f"map_mode must be live or final, got {map_mode!r}")
    if checkpoints is not None and checkpoints < 0:
        raise ValueError(f"checkpoints must be >= 0, got {checkpoints}")
    cfg = config or load_config()
    t_wall = time.perf_counter()
    start_ns, duration, truth = recording_span(log_path)
    stage = ContactStage(cfg.contact, cfg.alignment, vehicle=cfg.vehicle, batch=64)
    mapper = Mapper.from_config(cfg)
    events: list[Envelope] = []
    observations: list[Observation] = []
    fits: list[FitResult] = []
    next_report = [0]
    marks: list[int] = []
    if map_mode == "final" and checkpoints and duration > 0:
        step = duration / (checkpoints + 1)
        marks = [start_ns + int(step * (k + 1) * 1e9) for k in range(checkpoints)]
    by_growth = map_mode == "final" and checkpoints is None
    next_size = 0.0  # with by_growth: fit once the mapper holds this many observations
    planted = sorted(inject, key=lambda o: o.t_ns)

    def tick(recv_ns: int) -> None:
        if progress is not None and recv_ns >= next_report[0]:
            progress((recv_ns - start_ns) / 1e9, duration, len(fits), _begins(events))
            next_report[0] = recv_ns + 5_000_000_000

    for batch in _stage_batches(stage, log_path, cfg, tick, start, end, tap):
        batch_events, new = _split(batch)
        events.extend(batch_events)
        if not new:
            continue
        if planted:
            t_new = max(o.t_ns for o in new)
            while planted and planted[0].t_ns <= t_new:
                new.append(planted.pop(0))
        observations.extend(new)
        mapper.add(new)  # all of one detector output at once, as the live mapper receives it
        if map_mode == "live":
            if mapper.due():
                _append_fit(fits, mapper.refit(), keep_meshes)
        elif by_growth:
            if len(mapper) >= next_size and mapper.ready():
                _append_fit(fits, mapper.refit(), keep_meshes)
                next_size = len(mapper) * cfg.mapping.theta_refit_growth
        elif marks and max(o.t_ns for o in new) >= marks[0] and mapper.ready():
            marks.pop(0)
            _append_fit(fits, mapper.refit(), keep_meshes)
    if planted:  # planted after the last detector output
        observations.extend(planted)
        mapper.add(planted)
    if mapper.pending and mapper.ready():
        # the final map's kernel is learnt on everything, not on the last checkpoint's data
        _append_fit(fits, mapper.refit(learn_kernel=map_mode == "final"), keep_meshes)
    if progress is not None:
        progress(duration, duration, len(fits), _begins(events))
    return PipelineResult(
        log_path=str(log_path),
        mode="in-process",
        events=events,
        observations=observations,
        fits=fits,
        duration_s=duration,
        start_ns=start_ns,
        truth=truth,
        wall_s=time.perf_counter() - t_wall,
        stats={"detector": stage.stats.as_dict(), "mapper_duplicates": mapper.duplicates},
    )


def _begins(events: list[Envelope]) -> int:
    return sum(e.payload["state"] == "begin" for e in events)


def _append_fit(fits: list[FitResult], fit: FitResult, keep_meshes: int) -> None:
    fits.append(fit)
    # drop meshes of older fits (the last good mesh stays referenced by the newest result)
    for old in fits[: max(0, len(fits) - keep_meshes)]:
        if old.mesh is not None and old is not fits[-1] and old.mesh is not fits[-1].mesh:
            old.mesh = None
