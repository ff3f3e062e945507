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
from collections.abc import Callable

from groundstation.acquisition.reader import open_recording
from groundstation.acquisition.replay import iter_replay
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


def run_offline(
    log_path: str,
    config: Config | None = None,
    *,
    progress: Progress | None = None,
    keep_meshes: int = 3,
    start: float | None = None,
    end: float | None = None,
    tap: Callable[[Envelope], None] | None = None,
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
    start, end : float, optional
        Log window, seconds from the log start (``end`` exclusive): ``replay --start/--end``.
    tap : callable, optional
        Called with every decoded sample envelope before the detector sees it (replay outputs
        translate them to Foxglove channels without decoding the log twice).
    """
    cfg = config or load_config()
    t_wall = time.perf_counter()
    start_ns, duration, truth = recording_span(log_path)
    stage = ContactStage(cfg.contact, cfg.alignment)
    mapper = Mapper(cfg.mapper, cfg.mapping, cfg.surface)
    events: list[Envelope] = []
    observations: list[Observation] = []
    fits: list[FitResult] = []

    def handle(outs: list[Envelope]) -> None:
        for env in outs:
            if env.topic == "contact.event":
                events.append(env)
                continue
            obs = observation_from_envelope(env)
            observations.append(obs)
            mapper.add([obs])
            if mapper.due():
                _append_fit(fits, mapper.refit(), keep_meshes)

    next_report = 0
    for env in iter_replay(log_path, start, end, settings=cfg.acquisition):
        if env.topic not in INPUT_TOPICS:
            continue
        if tap is not None:
            tap(env)
        handle(stage.push(env))
        if progress is not None and env.header.recv_ns >= next_report:
            progress((env.header.recv_ns - start_ns) / 1e9, duration, len(fits), len(events))
            next_report = env.header.recv_ns + 5_000_000_000
    handle(stage.flush())
    if mapper.pending and mapper.ready():
        _append_fit(fits, mapper.refit(), keep_meshes)
    if progress is not None:
        progress(duration, duration, len(fits), len(events))
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


def _append_fit(fits: list[FitResult], fit: FitResult, keep_meshes: int) -> None:
    fits.append(fit)
    # drop meshes of older fits (the last good mesh stays referenced by the newest result)
    for old in fits[: max(0, len(fits) - keep_meshes)]:
        if old.mesh is not None and old is not fits[-1] and old.mesh is not fits[-1].mesh:
            old.mesh = None
