"""The mapper's fitting child: observations in, refits, plain-data reports out.

It holds the :class:`~groundstation.mapping.mapper.Mapper` of a mapper shell
(``runtime/workers/mapper.py``, whose docstring gives the protocol): it adds the observations
the shell sends, refits when one is due on the data clock, and reports each fit as plain data
(:func:`fit_message`), never as the mapping core's own objects.

Command line (started by the shell's ``FitChild``)::

    python -m groundstation.runtime.workers.fitchild --fd N --parent PID

``N`` is its end of a socket pair with the shell, used as a ``multiprocessing`` connection; the
shell's first message is ``("config", TOML text)``. It imports only what fitting needs, so that it
is ready as soon as the mapping core is imported.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import signal
import sys
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from groundstation.mapping.mapper import FitResult


def fit_message(fit: FitResult) -> dict:
    """The plain data (builtins and numpy arrays) of ``fit`` that the shell publishes."""
    from groundstation.mapping.mapper import REFIT_STAGES

    m = fit.mesh
    mesh: dict[str, Any] = {}
    if fit.reliable and m is not None:
        std = m.std if m.std is not None else np.zeros(len(m.vertices))
        mesh = {
            "vertices": np.ascontiguousarray(m.vertices, dtype=np.float32),
            "triangles": np.ascontiguousarray(m.faces, dtype=np.int32),
            "vertex_std": np.ascontiguousarray(std, dtype=np.float32),
        }
    return {
        "fit_index": int(fit.fit_index),
        "data_ns": int(fit.data_ns),
        "reliable": bool(fit.reliable),
        "reasons": tuple(str(r) for r in fit.reasons),
        "fit_s": float(fit.timings.get("total_s", 0.0)),
        "timings": {k: float(v) for k, v in fit.timings.items() if k in REFIT_STAGES},
        "hyperparameters": dict(fit.hyperparameters),
        "flagged_events": tuple(int(e) for e in fit.flagged_events),
        "ids": np.asarray(fit.ids, dtype=np.int64),
        "u": np.asarray(fit.u, dtype=np.float64),
        "flags": np.asarray(fit.flags),
        "awaiting_events": tuple(int(e) for e in fit.awaiting_events),
        **mesh,
    }


def _die_with(parent: int) -> None:
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:
        os._exit(75)


def fit_loop(conn: Any, config_text: str, parent: int) -> None:
    """Add observations, refit when due, report (see the module docstring)."""
    import tomllib

    from threadpoolctl import threadpool_limits

    from groundstation.config import load_config
    from groundstation.mapping.mapper import Mapper

    _die_with(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the shell decides when the child ends
    threadpool_limits(1)
    config = load_config(base=tomllib.loads(config_text))
    mapper = Mapper.from_config(config)
    conn.send(("idle", 0, 0))
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg[0] != "add":
            return
        _, batch, final = msg
        mapper.add(batch)
        if mapper.due() or (final and mapper.pending and mapper.ready()):
            conn.send(("fitting", mapper.fit_index + 1, len(mapper)))
            conn.send(("fit", fit_message(mapper.refit())))
        if final:
            conn.send(("finished", mapper.fit_index))
        conn.send(("idle", len(mapper), mapper.pending))


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring)."""
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.fitchild")
    p.add_argument("--fd", type=int, required=True, help="its end of the socket pair")
    p.add_argument("--parent", type=int, required=True, help="the shell's process id")
    args = p.parse_args(argv)
    _die_with(args.parent)  # before the imports: a shell gone meanwhile ends it at once
    conn = Connection(args.fd)
    try:
        kind, config_text = conn.recv()
    except (EOFError, OSError):
        return 0
    if kind != "config":
        print(f"fitting child: expected the configuration first, got {kind!r}", file=sys.stderr)
        return 2
    fit_loop(conn, config_text, args.parent)
    return 0


if __name__ == "__main__":
    sys.exit(main())
