"""The fitting child reports a fit to the mapper shell as plain data.

A pickled ``FitResult`` made the shell import the mapping core (scipy, scikit-image) when the
first fit arrived; on a loaded machine that held the first mesh back for about a second after
the fit had finished. The message built by :func:`fit_message` must unpickle in a fresh shell
without importing anything of the mapping core, and carry what the shell publishes.
"""

from __future__ import annotations

import dataclasses
import pickle
import subprocess
import sys

import numpy as np

from groundstation.contact.detector import Observation
from groundstation.mapping.mapper import Mapper, MapperSettings
from groundstation.runtime.workers.fitchild import fit_message
from groundstation.runtime.workers.mapper import FitMessage

S = 1_000_000_000

SHELL = """
import pickle, sys
before = set(sys.modules)
from groundstation.runtime.workers.mapper import FitMessage
shell = set(sys.modules)
msg = FitMessage.from_plain(pickle.loads(sys.stdin.buffer.read()))
added = sorted(set(sys.modules) - shell)
print(msg.fit_index, len(msg.vertices), ",".join(added))
"""


def _sphere_fit():
    rng = np.random.default_rng(1)
    c, out, i = np.array([1.0, -2.0, 1.0]), [], 0
    for k in range(40):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        p, t = c + 0.5 * n, k * S // 10
        out += [Observation(i, t, p, 0.0, np.zeros(3), k, 0.0),
                Observation(i + 1, t, p - 0.1 * n, -1.0, np.zeros(3), k, 0.0)]  # fmt: skip
        i += 2
    for k in range(80):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        p = c + rng.uniform(0.8, 1.2) * n
        out.append(Observation(i, 5 * S + k * S // 20, p, 1.0, np.zeros(3), -1, 0.0))
        i += 1
    m = Mapper(MapperSettings())
    m.add(out)
    return m.refit()


def test_a_fit_reaches_the_shell_without_the_mapping_core():
    fit = _sphere_fit()
    assert fit.reliable and fit.mesh is not None and len(fit.mesh.vertices) > 0
    plain = fit_message(fit)
    msg = FitMessage.from_plain(pickle.loads(pickle.dumps(plain)))
    assert msg.fit_index == fit.fit_index and msg.data_ns == fit.data_ns and msg.reliable
    assert np.array_equal(msg.ids, fit.ids) and np.array_equal(msg.flags, fit.flags)
    assert np.allclose(msg.u, fit.u, equal_nan=True)
    assert np.allclose(msg.vertices, fit.mesh.vertices, atol=1e-5)
    assert np.array_equal(msg.triangles, fit.mesh.faces)
    assert msg.vertices.dtype == np.float32 and msg.triangles.dtype == np.int32
    assert msg.fit_s == fit.timings["total_s"] and msg.flagged_events == fit.flagged_events
    waiting = FitMessage.from_plain(fit_message(dataclasses.replace(fit, awaiting_events=(7,))))
    assert msg.awaiting_events == () and waiting.awaiting_events == (7,)

    # a fresh interpreter with the shell's imports only: unpickling imports nothing new
    res = subprocess.run([sys.executable, "-c", SHELL], input=pickle.dumps(plain),
                         capture_output=True, timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr.decode()[-2000:]
    index, n_vertices, added = res.stdout.decode().split(" ", 2)
    assert int(index) == fit.fit_index and int(n_vertices) == len(fit.mesh.vertices)
    assert added.strip() == "", f"unpickling a fit imported: {added.strip()}"


def test_an_unreliable_fit_carries_no_mesh_to_publish():
    fit = dataclasses.replace(_sphere_fit(), reliable=False, reasons=("fit_error: boom",))
    msg = FitMessage.from_plain(fit_message(fit))
    assert not msg.reliable and msg.reasons == ("fit_error: boom",)
    assert msg.vertices is None and msg.triangles is None and msg.vertex_std is None
