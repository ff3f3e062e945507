"""The runtime room: how the stages run as processes of one session.

- :mod:`.session`: session endpoints (ipc paths per process, subscriber endpoints), stop signals,
  rate counters and the ``log`` helper every worker uses.
- :mod:`.supervisor`: starts the workers, restarts a crashed one with bounded backoff, stops them
  in reverse order.
- :mod:`.status`: the operator's status line, aggregated from every worker's ``status`` messages.
- :mod:`.sources`: which worker owns a ``serial://``, ``udp://``, ``natnet://`` or ``replay://``
  source.
- :mod:`.workers`: the process entry points (``python -m groundstation.runtime.workers.NAME``),
  each a thin shell that moves messages between the bus and a stage's pure core.

The stage folders (``acquisition``, ``contact``, ``mapping``, ``viewer``, ``pilot``) keep only
their pure cores and the I/O they own (device readers, the recording writer).
"""
