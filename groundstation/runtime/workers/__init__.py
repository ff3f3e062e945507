"""Process entry points of a session, one module per worker: ``link``, ``mocap``, ``recorder``,
``replay`` (sources and recording), ``detector``, ``mapper`` (the stages), ``viewer`` and
``pilot``. Each runs as ``python -m groundstation.runtime.workers.NAME --session ID ...``.
"""
