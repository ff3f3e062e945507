"""The pipeline as real processes on a session bus, for a replay source.

Workers (under :class:`~groundstation.runtime.supervisor.Supervisor`, session endpoints from
:mod:`groundstation.runtime.session`, publishers ``replay``, ``detector``, ``mapper``):

- ``replay``: ``python -m groundstation.runtime.workers.replay --uri replay://LOG?speed=...``
  (credit flow control at ``speed=max``: the detector is its one consumer);
- ``detector``: ``python -m groundstation.runtime.workers.detector --flow-from replay
  --wait-subscribers 2`` (the mapper and this collector);
- ``mapper``: ``python -m groundstation.runtime.workers.mapper --wait-subscribers 1``
  (``OPENBLAS_NUM_THREADS=1``).

This process subscribes to ``observations``, ``contact.event``, ``mapper.fit``, ``mesh`` and
``log``, counts sequence gaps, and stops the workers once the mapper has published its final
fit (``log`` "mapper finished: fit N" and that fit's ``mapper.fit``). The configuration is
resolved once here (or given resolved, e.g. by ``replay`` on top of the recorded one) and
written to the session directory, where every worker reads it.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence

import numpy as np

from groundstation.bus.pubsub import Subscriber
from groundstation.config import Config, to_toml
from groundstation.contact.stage import observation_from_envelope
from groundstation.errors import GroundstationError
from groundstation.mapping.mapper import FitResult
from groundstation.mapping.surface import SurfaceMesh
from groundstation.pipeline.offline import PipelineResult, recording_span
from groundstation.runtime.configuration import Resolved, resolve, write_session_config
from groundstation.runtime.session import REPLAY_PUBLISHER, Session, new_session_id
from groundstation.runtime.sources import source_worker
from groundstation.runtime.supervisor import Supervisor, WorkerSpec, python_module
from groundstation.runtime.workers.detector import DETECTOR_FINISHED

COLLECT = ("observations", "contact.event", "mapper.fit", "mesh", "log")


class PipelineProcessError(GroundstationError):
    """A worker died or the pipeline did not finish in time."""


def pipeline_workers(
    log_path: str,
    session: Session,
    speed: float = math.inf,
    config_path: str | None = None,
    overrides: Sequence[str] = (),
    window: str = "",
) -> list[WorkerSpec]:
    """Replay, detector and mapper workers of one replay session (command lines documented in
    the module docstring). With ``config_path`` / ``overrides`` every worker parses them;
    without, they read the session directory's ``config.toml``."""
    common: list[str] = []
    if config_path:
        common += ["--config", str(config_path)]
    for item in overrides:
        common += ["--set", item]
    speed_txt = "max" if math.isinf(speed) else repr(float(speed))
    replay = source_worker(
        f"replay://{log_path}?speed={speed_txt}{window}",
        session,
        REPLAY_PUBLISHER,
        ("--wait-subscribers", "1", *common),
    )
    detector = WorkerSpec(
        "detector",
        python_module(
            "groundstation.runtime.workers.detector", *session.as_args(), "--name", "detector",
            "--flow-from", REPLAY_PUBLISHER, "--wait-subscribers", "2", *common,
        ),
    )  # fmt: skip
    mapper = WorkerSpec(
        "mapper",
        python_module(
            "groundstation.runtime.workers.mapper", *session.as_args(), "--name", "mapper",
            "--wait-subscribers", "1", *common,
        ),
        env=(("OPENBLAS_NUM_THREADS", "1"), ("OMP_NUM_THREADS", "1")),
    )  # fmt: skip
    return [mapper, detector, replay]


def plain_timings(plain) -> dict[str, float]:
    """A ``mapper.fit`` message's ``timings``: its finite seconds by part, nothing else."""
    if not isinstance(plain, dict):
        return {}
    return {
        str(k): float(v)
        for k, v in plain.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    }


def _fit_from(env) -> FitResult:
    p, a = env.payload, env.arrays
    return FitResult(
        fit_index=int(p["fit_index"]),
        data_ns=int(p.get("data_ns", env.header.source_ns)),
        ids=np.array(a["ids"], dtype=np.int64),
        u=np.array(a["u"], dtype=np.float64),
        flags=np.array(a["flags"], dtype=np.uint8),
        flagged_events=(),
        mesh=None,
        mesh_fit_index=-1,
        timings={"total_s": float(p.get("fit_s", 0.0)), **plain_timings(p.get("timings"))},
        hyperparameters=dict(p.get("hyperparameters", {})),
        reliable=bool(p.get("reliable", True)),
        reasons=tuple(p.get("reasons", ())),
        awaiting_events=tuple(int(e) for e in p.get("awaiting_events", ())),
    )


def run_multiprocess(
    log_path: str,
    *,
    speed: float = math.inf,
    config_path: str | None = None,
    overrides: Sequence[str] = (),
    timeout_s: float = 600.0,
    progress: Callable[[str], None] | None = None,
    session_root: str = "/tmp",
    config: Config | None = None,
    start: float | None = None,
    end: float | None = None,
) -> PipelineResult:
    """Run the pipeline as processes on ``log_path`` and collect what they publish.

    The configuration is ``config`` when given (already resolved), else ``config_path`` and
    ``overrides`` resolved once here; either way the workers read it from the session directory.

    Raises
    ------
    PipelineProcessError
        A worker exited early, or the mapper did not finish within ``timeout_s``.
    """
    t_wall = time.perf_counter()
    start_ns, duration, truth = recording_span(log_path)
    resolved = (
        resolve(config_path, overrides)
        if config is None
        else Resolved(config, to_toml(config), base="given")
    )
    session = Session(new_session_id(), (REPLAY_PUBLISHER, "detector", "mapper"), session_root)
    session.write_info(command="replay")
    write_session_config(session.directory, resolved)
    sub = Subscriber(session.subscribe_endpoints(), COLLECT)
    window = "".join(f"&{k}={v!r}" for k, v in (("start", start), ("end", end)) if v is not None)
    sup = Supervisor(pipeline_workers(log_path, session, speed, window=window))
    events, observations, fits = [], [], []
    last_mesh: tuple[int, SurfaceMesh] | None = None
    detector_summary: dict = {}
    final_index: int | None = None
    previous = _terminate_as_interrupt()
    try:
        sup.start()
        deadline = time.monotonic() + timeout_s
        got_final = False
        while not got_final:
            if time.monotonic() > deadline:
                raise PipelineProcessError(
                    f"pipeline on {log_path} did not finish in {timeout_s} s"
                )
            env = sub.recv(500)
            if env is None:
                for ev in sup.poll():
                    if ev.kind in ("exited", "gave_up") and ev.name != REPLAY_PUBLISHER:
                        raise PipelineProcessError(
                            f"worker {ev.name} exited ({ev.returncode}) before the end"
                        )
                continue
            t = env.topic
            if t == "contact.event":
                events.append(env)
            elif t == "observations":
                observations.append(observation_from_envelope(env))
            elif t == "mesh":
                a = env.arrays
                v = np.array(a["vertices"], dtype=np.float64)
                mesh = SurfaceMesh(
                    v,
                    np.array(a["triangles"], dtype=np.int64),
                    np.zeros_like(v),
                    np.array(a["vertex_std"], dtype=np.float64),
                )
                last_mesh = (int(env.payload["fit_index"]), mesh)
            elif t == "mapper.fit":
                fits.append(_fit_from(env))
                if progress is not None:
                    f = fits[-1]
                    progress(f"fit {f.fit_index} at {(f.data_ns - start_ns) / 1e9:.1f} s log")
            elif t == "log":
                msg = env.payload.get("message", "")
                if msg.startswith(DETECTOR_FINISHED):
                    detector_summary = json.loads(msg.partition(": ")[2])
                elif msg.startswith("mapper finished"):
                    final_index = int(msg.rsplit(" ", 1)[1])
            if final_index is not None:
                got_final = final_index < 0 or any(f.fit_index == final_index for f in fits)
        gaps = {k: s.gaps for k, s in sub.stats.items()}
    finally:
        sub.close()
        sup.stop(timeout_s=10)
        session.cleanup()
        _restore(previous)
    if fits and last_mesh is not None:
        fits[-1].mesh, fits[-1].mesh_fit_index = last_mesh[1], last_mesh[0]
    if fits:
        fits[-1].flagged_events = _flagged_events(observations, fits[-1])
    for topic, n in detector_summary.get("gaps", {}).items():
        gaps[f"detector:{topic}"] = n
    return PipelineResult(
        log_path=str(log_path),
        mode="multi-process",
        events=events,
        observations=observations,
        fits=fits,
        duration_s=duration,
        start_ns=start_ns,
        truth=truth,
        wall_s=time.perf_counter() - t_wall,
        gaps=gaps,
        stats={"detector": detector_summary.get("stage", {})},
    )


def _terminate_as_interrupt():
    """SIGTERM -> KeyboardInterrupt while the workers run, so ``finally`` stops them in order
    (a SIGKILLed parent takes them along by their parent-death signal). Main thread only."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    return signal.signal(signal.SIGTERM, handler)


def _restore(previous) -> None:
    import signal

    if previous is not None:
        signal.signal(signal.SIGTERM, previous)


def _flagged_events(observations, fit: FitResult) -> tuple[int, ...]:
    flagged = set(fit.ids[(fit.flags & 1) == 1].tolist())
    return tuple(sorted({o.event_id for o in observations if o.id in flagged and o.label == 0}))
