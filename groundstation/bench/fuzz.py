"""``groundstation bench fuzz``: millions of hostile inputs per parser, in a watched child.

Every parser that takes bytes from outside (the wire, other processes, files) must raise only
its declared errors, stay fast on every input and never hang (issue 14). A *target* is one such
parser with its declared error classes and seed inputs (:mod:`groundstation.bench.fuzz_targets`):

=============  ===========================================================  =================
target         what runs on each input                                      declared errors
=============  ===========================================================  =================
``envelope``   bus ``decode`` of multipart frames (with the topic table)    EnvelopeError
               and ``from_bytes`` of recorded blobs
``natnet``     ``parse_packet`` (each version), then the stream decoder;    NatNetParseError
               every pose it yields must encode as a bus message             (parse only)
``mavlink``    the MAVLink stream decoder on the input cut into chunks      none
               (CRC-valid frames of every ``common`` message with random
               payloads, damaged streams); every sample must encode
``mcap``       a recording read from memory: open, verify, every message,   GroundstationError
               metadata, truth
``csv``        the CSV importer's parser on text, then the unit conversion  ImportDataError
               and the checks every imported stream passes
``tlog``       the tlog record reader                                       none
``ulog``       pyulog (third-party) and our conversion, in process          ImportDataError
=============  ===========================================================  =================

Inputs are mutations of valid seeds (bit flips, interesting integers and floats such as 1e291,
inf and 2**63, inserted/deleted/duplicated blocks, splices, truncation) plus structured
generators per target (deep JSON, huge dimensions, CRC-valid frames with random payloads, chunks
with recomputed CRCs). Input ``i`` is a pure function of ``(seed, target, i)``, so any finding is
reproduced from its index, and every finding's bytes are written to ``--out``.

The target runs in a child process; the parent watches its progress and kills it when one input
has run for ``hang_s`` (a hang: recorded with its reproducer, then the child restarts after that
input). An input is *slow* when it takes more than ``slow_ms`` of wall time twice more when re-run
alone (a loaded machine makes single wall-time outliers: those are counted as ``noise``, never as
slow). Pure apart from the child process and the files under ``--out``.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import random
import time
import traceback
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from groundstation.bench.fuzz_targets import HANG_S, TARGETS, Target, mutate
from groundstation.errors import ConfigError

__all__ = ["HANG_S", "SLOW_MS", "TARGETS", "Target", "TargetResult", "mutate", "run_target"]

#: Wall time above which an input counts as slow (confirmed by re-running it), ms.
SLOW_MS = 100.0
_SNAPSHOT_EVERY = 500
_MAX_REPRO_BYTES = 1 << 20

# -- results ------------------------------------------------------------------------------------


@dataclass
class Finding:
    """One kind of undeclared exception (or a hang / a slow input) and its first reproducer."""

    kind: str
    count: int
    first_index: int
    detail: str
    reproducer: str = ""  # file name under --out


@dataclass
class TargetResult:
    """Totals of one target."""

    target: str
    inputs: int = 0
    declared: int = 0
    crashes: int = 0
    hangs: int = 0
    slow: int = 0
    slow_noise: int = 0
    stalls: int = 0
    wall_s: float = 0.0
    max_ms: float = 0.0
    p99_ms: float = 0.0
    findings: list[Finding] = field(default_factory=list)
    in_memory: bool = True

    @property
    def inputs_per_s(self) -> float:
        return self.inputs / self.wall_s if self.wall_s > 0 else 0.0

    @property
    def clean(self) -> bool:
        return self.crashes == 0 and self.hangs == 0 and self.slow == 0

    def as_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != "findings"}
        d["inputs_per_s"] = round(self.inputs_per_s, 1)
        d["findings"] = [f.__dict__ for f in self.findings]
        return d


def input_rng(seed: int, target: str, index: int) -> random.Random:
    """The generator of input ``index`` of ``target`` (inputs are reproducible one by one)."""
    return random.Random(f"{seed}:{target}:{index}")


def _kind(exc: BaseException) -> str:
    """Exception type + innermost frame: what makes two crashes "the same"."""
    tb = traceback.extract_tb(exc.__traceback__)
    where = f"{Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else "?"
    return f"{type(exc).__name__} at {where}"


class _Stall(BaseException):  # noqa: N818 - not an error: a time limit (like KeyboardInterrupt)
    """Raised by SIGALRM in a library target's child: the input hit its time limit (a
    BaseException, so that no ``except Exception`` inside the library swallows it)."""


def _on_alarm(signum: int, frame: Any) -> None:
    raise _Stall()


def _child(name: str, seed: int, start: int, stop: int, skip: frozenset, progress, conn) -> None:
    """Run inputs ``start..stop`` of ``name`` (not ``skip``); report through ``conn``."""
    import signal

    target = TARGETS[name]
    generate, run = target.make()
    declared = target.declared()
    stall_s = target.stall_s
    if stall_s:
        signal.signal(signal.SIGALRM, _on_alarm)
    stalls = 0
    declared_n = 0
    done = start
    times_hist: Counter = Counter()  # ms bucket -> count (for p99)
    max_ms = 0.0
    crash_counts: Counter = Counter()

    def snapshot(final: bool) -> None:
        conn.send(
            ("snapshot", done, declared_n, dict(crash_counts), dict(times_hist), max_ms, stalls,
             final)
        )  # fmt: skip

    perf = time.perf_counter
    for i in range(start, stop):
        if i in skip:
            done = i + 1
            continue
        progress.value = i
        try:
            x = generate(input_rng(seed, name, i))
        except Exception as exc:  # a bug of the bench itself, not a finding: stop loudly
            conn.send(("generator", i, f"{type(exc).__name__}: {exc}"))
            conn.close()
            return
        t0 = perf()
        try:
            if stall_s:
                signal.setitimer(signal.ITIMER_REAL, stall_s)
            try:
                run(x)
            finally:
                if stall_s:
                    signal.setitimer(signal.ITIMER_REAL, 0)
        except _Stall:
            stalls += 1
            if stalls == 1:
                conn.send(("stall", i))
            done = i + 1
            continue
        except declared:
            declared_n += 1
        except Exception as exc:  # noqa: BLE001 - exactly what we are looking for
            k = _kind(exc)
            if crash_counts[k] == 0:
                conn.send(("crash", k, i, f"{type(exc).__name__}: {str(exc)[:300]}"))
            crash_counts[k] += 1
        ms = (perf() - t0) * 1e3
        if ms > max_ms:
            max_ms = ms
        times_hist[min(int(ms * 10), 100_000)] += 1  # 0.1 ms buckets
        if ms > SLOW_MS:  # confirm here, under the same limits: slow twice more alone?
            again = []
            for _ in range(2):
                t1 = perf()
                try:
                    if stall_s:
                        signal.setitimer(signal.ITIMER_REAL, stall_s)
                    try:
                        run(generate(input_rng(seed, name, i)))
                    finally:
                        if stall_s:
                            signal.setitimer(signal.ITIMER_REAL, 0)
                except BaseException:  # noqa: BLE001 - only the time matters here
                    pass
                again.append((perf() - t1) * 1e3)
            conn.send(("slow", i, ms, again))
        done = i + 1
        if done % _SNAPSHOT_EVERY == 0:
            snapshot(False)
    progress.value = stop
    snapshot(True)
    conn.close()


def _save(out: Path | None, name: str, seed: int, index: int, tag: str) -> str:
    if out is None:
        return ""
    x = TARGETS[name].make()[0](input_rng(seed, name, index))
    path = out / f"{name}-{tag}-{index}.json"
    path.write_text(json.dumps({"target": name, "seed": seed, "index": index,
                                "input": _jsonable(x)})[: _MAX_REPRO_BYTES * 3])  # fmt: skip
    return path.name


def _jsonable(x: Any) -> Any:
    if isinstance(x, bytes | bytearray):
        return {"hex": bytes(x).hex()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    return x


def run_target(
    name: str,
    inputs: int,
    *,
    seed: int = 0,
    out: Path | None = None,
    hang_s: float | None = None,
    progress: Callable[[str], None] | None = None,
) -> TargetResult:
    """Fuzz one target with ``inputs`` inputs in a watched child process.

    Raises
    ------
    ConfigError
        Unknown target or a non-positive number of inputs.
    """
    if name not in TARGETS:
        raise ConfigError(f"unknown fuzz target {name!r}", hint=f"one of {', '.join(TARGETS)}")
    hang_s = TARGETS[name].hang_s if hang_s is None else hang_s
    if inputs < 1 or not hang_s > 0:
        raise ConfigError(f"--inputs ({inputs}) must be >= 1 and --hang-s ({hang_s}) > 0")
    ctx = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods()
                                      else "spawn")  # fmt: skip
    res = TargetResult(name, in_memory=TARGETS[name].in_memory)
    findings: dict[str, Finding] = {}
    hist: Counter = Counter()
    slow_seen: dict[int, tuple[float, list[float]]] = {}  # by index: a re-run segment repeats
    start, skip = 0, set()
    first_stall: int | None = None
    t0 = time.monotonic()
    last_report = t0
    while start < inputs:
        recv, send = ctx.Pipe(duplex=False)
        shared = ctx.Value("q", start)
        proc = ctx.Process(
            target=_child, args=(name, seed, start, inputs, frozenset(skip), shared, send),
            daemon=True,
        )  # fmt: skip
        proc.start()
        send.close()
        last_value, last_change = shared.value, time.monotonic()
        snap = (start, 0, {}, {}, 0.0, 0)
        finished = False
        while not finished:
            if recv.poll(0.2):
                try:
                    msg = recv.recv()
                except (EOFError, OSError):  # the child is gone: handled just below
                    proc.join(5)
                    msg = ("gone",)
                if msg[0] == "generator":
                    proc.kill()
                    raise RuntimeError(f"fuzz target {name!r}: input {msg[1]} generator: {msg[2]}")
                if msg[0] == "crash":
                    _, kind, index, detail = msg
                    findings.setdefault(kind, Finding(kind, 0, index, detail))
                elif msg[0] == "slow":
                    slow_seen[msg[1]] = (msg[2], msg[3])
                elif msg[0] == "stall":
                    first_stall = msg[1] if first_stall is None else first_stall
                elif msg[0] == "snapshot":
                    done, dec, crashes, h, mx, st, final = msg[1:]
                    snap = (done, dec, crashes, h, mx, st)
                    finished = final
                if msg[0] != "gone":
                    continue
            now = time.monotonic()
            value = shared.value
            if value != last_value:
                last_value, last_change = value, now
            elif now - last_change > hang_s and value < inputs:
                proc.kill()
                proc.join(5)
                hang = Finding("hang", 1, value, f"input {value} ran for more than {hang_s} s")
                hang.reproducer = _save(out, name, seed, value, "hang")
                findings[f"hang {value}"] = hang
                res.hangs += 1
                skip.add(value)
                break
            if not proc.is_alive() and not recv.poll(0):
                crash = Finding(
                    f"worker died (exit {proc.exitcode})", 1, value,
                    f"the child process died on input {value}",
                )  # fmt: skip
                crash.reproducer = _save(out, name, seed, value, "died")
                findings[f"died {value}"] = crash
                res.crashes += 1
                skip.add(value)
                break
            if progress is not None and now - last_report >= 10:
                last_report = now
                progress(f"fuzz {name}: {value:,}/{inputs:,} inputs, {len(findings)} finding(s)")
        done, dec, crashes, h, mx, st = snap
        res.declared += dec
        res.stalls += st
        res.crashes += sum(crashes.values())
        for kind, n in crashes.items():
            if kind in findings:
                findings[kind].count += n
        hist.update(h)
        res.max_ms = max(res.max_ms, mx)
        recv.close()
        proc.join(5)
        if proc.is_alive():
            proc.kill()
        start = done if not finished else inputs
        if not finished and start in skip:
            start += 1
    res.wall_s = time.monotonic() - t0
    res.inputs = inputs
    for f in findings.values():
        if f.kind.startswith(("hang", "worker")):
            continue
        f.reproducer = _save(out, name, seed, f.first_index, "crash")
    for index, (ms, again) in sorted(slow_seen.items()):  # slow twice more alone, or noise
        if min(again) > SLOW_MS:
            res.slow += 1
            f = Finding("slow", 1, index, f"{ms:.0f} ms, then {again[0]:.0f}/{again[1]:.0f} ms")
            f.reproducer = _save(out, name, seed, index, "slow")
            findings[f"slow {index}"] = f
        else:
            res.slow_noise += 1
    total = sum(hist.values())
    acc = 0
    for bucket in sorted(hist):
        acc += hist[bucket]
        if acc >= 0.99 * total:
            res.p99_ms = bucket / 10
            break
    if first_stall is not None:
        f = Finding(
            "library stall", res.stalls, first_stall,
            f"stopped at the {TARGETS[name].stall_s} s time limit, as the importer does",
        )  # fmt: skip
        f.reproducer = _save(out, name, seed, first_stall, "stall")
        findings["library stall"] = f
    res.findings = list(findings.values())
    return res


def table(results: Sequence[TargetResult]) -> str:
    """Markdown table of the results."""
    lines = [
        "| target | inputs | inputs/s | wall s | declared errors | undeclared exceptions | "
        "hangs | library stalls | slow (> 100 ms) | p99 ms | max ms |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        noise = f" (+{r.slow_noise} noise)" if r.slow_noise else ""
        stalls = str(r.stalls) if not r.in_memory else "-"
        lines.append(
            f"| {r.target}{'' if r.in_memory else ' (library)'} | {r.inputs:,} | "
            f"{r.inputs_per_s:,.0f} | {r.wall_s:,.0f} | {r.declared:,} | {r.crashes} | {r.hangs} | "
            f"{stalls} | {r.slow}{noise} | {r.p99_ms:.1f} | {r.max_ms:.1f} |"
        )
    for r in results:
        for f in r.findings:
            where = f" -> {f.reproducer}" if f.reproducer else ""
            lines.append(f"- {r.target}: {f.kind} x{f.count} (first input {f.first_index}): "
                         f"{f.detail}{where}")  # fmt: skip
    return "\n".join(lines)


def write_results(results: Sequence[TargetResult], out: Path, seed: int) -> None:
    """``fuzz.json`` and ``fuzz.md`` under ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    doc = {"seed": seed, "slow_ms": SLOW_MS, "cpu_count": os.cpu_count(),
           "targets": [r.as_dict() for r in results]}  # fmt: skip
    (out / "fuzz.json").write_text(json.dumps(doc, indent=1) + "\n")
    (out / "fuzz.md").write_text(table(results) + "\n")
