"""The supervisor with real child processes: restart after a crash, give up, clean stop."""

from __future__ import annotations

import sys
import time

from groundstation.runtime.supervisor import Supervisor, WorkerSpec


def _wait_for(predicate, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def test_crashed_worker_is_restarted_then_given_up(tmp_path):
    counter = tmp_path / "starts"
    script = f"open({str(counter)!r}, 'a').write('x'); raise SystemExit(3)"
    spec = WorkerSpec("crashy", (sys.executable, "-c", script), max_restarts=2, backoff_s=0.01)
    sup = Supervisor([spec])
    events = sup.start()
    seen = list(events)
    assert _wait_for(lambda: (seen.extend(sup.poll()), any(e.kind == "gave_up" for e in seen))[1])
    kinds = [e.kind for e in seen]
    assert kinds.count("started") == 3  # first start + 2 restarts
    assert kinds.count("restarting") == 2
    assert all(e.returncode == 3 for e in seen if e.kind == "exited")
    assert counter.read_text() == "xxx"
    sup.stop()


def test_clean_exit_is_not_restarted():
    sup = Supervisor([WorkerSpec("done", (sys.executable, "-c", "pass"))])
    sup.start()
    seen = []
    assert _wait_for(lambda: (seen.extend(sup.poll()), any(e.kind == "exited" for e in seen))[1])
    time.sleep(0.1)
    seen.extend(sup.poll())
    assert [e.kind for e in seen] == ["exited"]


def test_stop_escalates_to_sigterm_for_a_worker_that_ignores_sigint():
    script = (
        "import signal, time, sys\n"
        "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
        "print('ready', flush=True)\n"
        "time.sleep(60)\n"
    )
    import subprocess

    sup = Supervisor(
        [WorkerSpec("stubborn", (sys.executable, "-c", script))], stdout=subprocess.PIPE
    )
    sup.start()
    proc = sup._workers["stubborn"].proc
    assert proc.stdout.readline().strip() == b"ready"
    events = sup.stop(timeout_s=0.3)
    assert events[0].kind == "stopped" and events[0].detail == "SIGTERM"
    assert sup.alive() == {"stubborn": False}


def test_restart_policy_follows_the_time_given():
    """The first restart in the window is immediate (a restart window loses data); the next
    ones back off."""
    spec = WorkerSpec("x", (sys.executable, "-c", "raise SystemExit(1)"), backoff_s=4.0)
    sup = Supervisor([spec])
    sup.start()
    sup._workers["x"].proc.wait(10)
    events = sup.poll(now=1000.0)
    assert [e.kind for e in events] == ["exited", "restarting", "started"]
    assert events[-1].restarts == 1
    sup._workers["x"].proc.wait(10)
    assert [e.kind for e in sup.poll(now=1001.0)] == ["exited", "restarting"]
    assert sup.poll(now=1004.0) == []  # backoff (4 s) not yet elapsed
    assert [e.kind for e in sup.poll(now=1005.5)] == ["started"]
    sup.stop()


def test_workers_share_one_process_group_apart_from_the_supervisor_and_know_their_parent():
    import os

    script = "import os; print(os.getpgid(0), os.environ['GS_SUPERVISOR_PID'], flush=True)"
    import subprocess

    specs = [WorkerSpec(n, (sys.executable, "-c", script)) for n in ("a", "b")]
    sup = Supervisor(specs, stdout=subprocess.PIPE)
    sup.start()
    out = [sup._workers[n].proc.stdout.readline().split() for n in ("a", "b")]
    sup.stop()
    groups = {int(g) for g, _ in out}
    assert len(groups) == 1 and groups != {os.getpgid(0)}
    assert {int(p) for _, p in out} == {os.getpid()}


def test_a_warm_spare_takes_over_a_dead_worker(tmp_path):
    """A ``warm`` worker's spare interpreter (imports done) replaces it when it dies."""
    import os
    import signal

    marker = tmp_path / "pids"
    module = "tests.integration.spare_target"
    spec = WorkerSpec("w", (sys.executable, "-m", module, str(marker)), warm=True)
    sup = Supervisor([spec], spare_delay_s=0.0)
    sup.start()
    first = sup.pid("w")
    assert _wait_for(lambda: marker.exists() and marker.read_text().strip())
    assert _wait_for(lambda: (sup.poll(), sup._workers["w"].spare is not None)[1])
    spare = sup._workers["w"].spare.pid
    os.kill(first, signal.SIGKILL)
    seen = []
    assert _wait_for(lambda: (seen.extend(sup.poll()), any(e.kind == "started" for e in seen))[1])
    assert sup.pid("w") == spare and "warm spare" in seen[-1].detail
    assert _wait_for(lambda: marker.exists() and len(marker.read_text().split()) >= 2)
    assert marker.read_text().split()[-1] == f"{spare}:1"  # incarnation 1, the spare's pid
    sup.stop()


def test_spares_start_one_after_another_not_all_at_once(tmp_path):
    """At start the warm spares follow one another (in start order, cold workers skipped):
    all importing at once competed with the session's start (the mapper's fitting child)."""
    module = "tests.integration.spare_target"
    specs = [WorkerSpec(n, (sys.executable, "-m", module, str(tmp_path / n)), warm=w)
             for n, w in (("a", True), ("cold", False), ("b", True), ("c", True))]  # fmt: skip
    sup = Supervisor(specs, spare_delay_s=1.0, spare_stagger_s=10.0)
    t0 = time.monotonic()
    sup.start()
    try:
        spares = {}
        for dt in (0.5, 5.0, 15.0, 25.0):  # margins for a slow start() on a loaded machine
            sup.poll(now=t0 + dt)
            spares[dt] = sorted(n for n, w in sup._workers.items() if w.spare is not None)
        assert spares == {0.5: [], 5.0: ["a"], 15.0: ["a", "b"], 25.0: ["a", "b", "c"]}
    finally:
        sup.stop()
