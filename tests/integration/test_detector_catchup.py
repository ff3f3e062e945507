"""A SIGKILLed detector resumes exactly: no contact event or observation lost or doubled.

A bundled flight is published by the replay source (paced at 4x, one publisher, so the detector
sees the samples in the recorded order), recorded by the recorder, and processed by the
detector, which is SIGKILLed mid-flight; the supervisor restarts it and it catches up from its
checkpoint and the recording. Its recorded outputs must equal what the detector core makes of
the flight in one pass (``iter_replay`` + ``ContactStage``): same ids, states, labels and data
times, each once. An output the killed detector handed to ZeroMQ may have reached the test's
subscriber and not the recorder (one did, once in a fresh-clone CI run): the resumed detector
sends its last outputs again and the recorder keeps the first copy of each.
"""

from __future__ import annotations

import os
import shutil
import signal
import time
import warnings
from pathlib import Path

import pytest

from groundstation.acquisition.replay import iter_replay
from groundstation.acquisition.segments import open_session
from groundstation.bus.envelope import from_bytes
from groundstation.bus.pubsub import Subscriber
from groundstation.contact.stage import INPUT_TOPICS, ContactStage
from groundstation.runtime.configuration import resolve, write_session_config
from groundstation.runtime.session import Session, new_session_id
from groundstation.runtime.supervisor import Supervisor, WorkerSpec, python_module
from groundstation.runtime.workers.detector import DETECTOR_FINISHED
from tests.integration.live_session import private_root

pytestmark = pytest.mark.timeout(300)
LOG = Path(__file__).resolve().parents[2] / "replay_logs" / "wall_survey.mcap"


def _key(env) -> tuple:
    p = env.payload
    return (env.topic, int(p["id"]), p.get("state", p.get("label")), int(env.header.source_ns))


def test_a_killed_detector_resumes_from_its_checkpoint_and_the_recording(tmp_path, zctx):
    root = private_root()
    session = Session(new_session_id(), ("replay", "recorder", "detector"), root)
    session.write_info()
    write_session_config(session.directory, resolve())
    out = tmp_path / "rec.mcap"
    w = session.as_args()
    specs = [
        WorkerSpec("recorder", python_module("groundstation.runtime.workers.recorder", *w,
                                             "--out", str(out), "--no-standby")),
        WorkerSpec("detector", python_module("groundstation.runtime.workers.detector", *w,
                                             "--wait-subscribers", "2", "--recording", str(out))),
        WorkerSpec("replay", python_module("groundstation.runtime.workers.replay", *w,
                                           "--uri", f"replay://{LOG}?speed=4",
                                           "--wait-subscribers", "2"), restart=False),
    ]  # fmt: skip
    sub = Subscriber(session.subscribe_endpoints(), ["observations", "log"], context=zctx)
    sup = Supervisor(specs)
    killed = False
    finished = []
    try:
        sup.start()
        deadline = time.monotonic() + 240
        n_obs = 0
        while not finished and time.monotonic() < deadline:
            env = sub.recv(200)
            sup.poll()
            if env is None:
                continue
            if env.topic == "observations":
                n_obs += 1
                if n_obs == 60 and not killed:  # mid-flight, in the middle of the contacts
                    os.kill(sup.pid("detector"), signal.SIGKILL)
                    killed = True
            elif env.payload.get("message", "").startswith(DETECTOR_FINISHED):
                finished.append(env.payload["message"])
        assert killed and finished, f"killed={killed} finished={finished}"
        time.sleep(1.5)  # the recorder closes a chunk at least once a second
    finally:
        sub.close()
        sup.stop(timeout_s=20)
        shutil.rmtree(root, ignore_errors=True)

    stage = ContactStage()
    expected = []
    for env in iter_replay(str(LOG)):
        if env.topic in INPUT_TOPICS:
            expected += stage.push(env)
    expected += stage.flush()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with open_session(out) as rec:
            got = [from_bytes(m.data) for m in rec.messages(["observations", "contact.event"])]
            logs = [from_bytes(m.data).payload["message"] for m in rec.messages("log")]
    keys = [_key(e) for e in got]
    assert len(keys) == len(set(keys)), "an output was published twice"
    want = {_key(e) for e in expected}
    assert set(keys) == want, (
        f"{len(want - set(keys))} outputs lost, {len(set(keys) - want)} differ: "
        f"{sorted(want ^ set(keys))[:5]}"
    )
    resumed = [m for m in logs if m.startswith("resumed from its checkpoint")]
    assert resumed and "lost" not in resumed[0], logs
    assert " 0 re-sent" not in resumed[0], resumed[0]  # the send queue's last outputs went again
    assert len({e.header.origin for e in got}) == 2  # two incarnations published
    print(f"\n{len(keys)} outputs identical to one pass of the core; {resumed[0]}")
