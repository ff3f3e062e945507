"""Bus probe: subscribe, count and time messages, print a JSON summary.

A debugging tool (and the out-of-process subscriber of the bus integration tests)::

    python -m groundstation.bus.probe tcp://127.0.0.1:5555 --topics samples.imu,status --count 600

The summary holds per-topic counters (received, gaps, first/last seq, bad) and the
publish->receive latency percentiles (``recv_ns - source_ns``; meaningful when the publisher
stamps ``source_ns`` with the station monotonic clock, which is shared by processes on a host).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence

import numpy as np

from groundstation.bus.pubsub import Subscriber


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.bus.probe", description=__doc__)
    p.add_argument("endpoints", nargs="+", help="publisher endpoints to connect to")
    p.add_argument("--topics", default="", help="comma-separated topics (default: all)")
    p.add_argument("--count", type=int, default=0, help="stop after this many messages (0: none)")
    p.add_argument("--timeout-s", type=float, default=10.0, help="stop after this long idle")
    p.add_argument("--flow", default=None, help="publisher flow endpoint (credit flow control)")
    p.add_argument("--delay-ms", type=float, default=0.0, help="processing time per message")
    p.add_argument("--server-key", default=None, help="CURVE server public key (Z85)")
    return p


def run(argv: Sequence[str] | None = None) -> dict:
    """Run the probe and return its summary (see the module docstring)."""
    args = _parser().parse_args(argv)
    topics = [t for t in args.topics.split(",") if t] or None
    key = args.server_key.encode() if args.server_key else None
    lat: list[int] = []
    n = 0
    with Subscriber(args.endpoints, topics, server_public_key=key, flow_endpoint=args.flow) as sub:
        print(json.dumps({"ready": True}), flush=True)
        while not args.count or n < args.count:
            env = sub.recv(int(args.timeout_s * 1000))
            if env is None:
                break
            n += 1
            lat.append(env.header.recv_ns - env.header.source_ns)
            if args.delay_ms:
                time.sleep(args.delay_ms / 1000)
        summary = {
            "received": n,
            "topics": {k: s.as_dict() for k, s in sub.stats.items()},
            "bad_messages": sub.bad_messages,
            "last_error": sub.last_error,
        }
    if lat:
        p50, p99 = np.percentile(np.asarray(lat, dtype=np.float64) / 1e3, [50, 99])
        summary["latency_us"] = {"p50": float(p50), "p99": float(p99), "n": len(lat)}
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: print the summary as one JSON line; exit 0."""
    print(json.dumps(run(argv)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
