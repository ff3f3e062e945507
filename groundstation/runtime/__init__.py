"""The runtime room: how the stages run as processes of one session.

- :mod:`.session`: session endpoints (ipc paths per process, subscriber endpoints), the session's
  ``session.json``, stop signals, rate counters and the ``log`` helper.
- :mod:`.worker`: the one process shell every worker runs on (signals, parent death, ready
  handshake, status, shutdown) and :func:`~.worker.worker_main`.
- :mod:`.configuration`: the configuration resolved once per session, written to the session
  directory, read by every worker, the recorded one as a replay's base.
- :mod:`.supervisor`: starts the workers in one process group, restarts a crashed one (from a
  warm spare, :mod:`.spare`), stops them in reverse order.
- :mod:`.catchup`: what a restarted worker missed, from the recorded stream; :mod:`.statefile`:
  the few integers that outlive a worker; :mod:`.tap`: the recorders' header-only subscriber.
- :mod:`.status` and :mod:`.alerts`: the operator's status line and what it must say in upper
  case, aggregated from every worker's ``status`` messages and the supervisor's events.
- :mod:`.sources`: which worker owns a ``serial://``, ``udp://``, ``natnet://`` or ``replay://``
  source.
- :mod:`.workers`: the process entry points (``python -m groundstation.runtime.workers.NAME``),
  each a thin shell that moves messages between the bus and a stage's pure core.

The stage folders (``acquisition``, ``contact``, ``mapping``, ``viewer``, ``pilot``) keep only
their pure cores and the I/O they own (device readers, the recording writer).
"""
