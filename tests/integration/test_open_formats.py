"""Replay outputs in open formats (issue 15), through the real command on every bundled log:

- ``replay.mcap`` decodes with ``foxglove_schemas_protobuf`` alone (and with the schemas the
  file carries, through protobuf's descriptor pool): mesh, contacts, trajectory, pose, signal,
  events and logs are there; it is itself a replayable station recording;
- ``report.html`` renders in headless Chromium, offline, with its plots and event table;
- ``export foxglove`` adds the same channels to a recording made before them;
- ``--start/--end`` replay a window; a foreign MCAP file is an error.

No project decoder reads the Foxglove channels here: ``mcap``'s reader and the schema classes do.
"""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pool, message_factory
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from mcap.reader import make_reader

ROOT = Path(__file__).resolve().parents[2]
LOGS = sorted((ROOT / "replay_logs").glob("*.mcap"))
REQUIRED = {
    "/map/mesh": "foxglove.SceneUpdate",
    "/map/contacts": "foxglove.PointCloud",
    "/vehicle/trajectory": "foxglove.SceneUpdate",
    "/vehicle/pose": "foxglove.PoseInFrame",
    "/tf": "foxglove.FrameTransform",
    "/vehicle/attitude": "foxglove.PoseInFrame",
    "/imu/accel": "foxglove.Vector3",
    "/detector/signal": "foxglove.Vector3",
    "/detector/events": "foxglove.Event",
    "/log": "foxglove.Log",
}

pytestmark = pytest.mark.timeout(600)


def gs(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "groundstation.cli", *args],
        capture_output=True, text=True, timeout=timeout, cwd=ROOT,
    )  # fmt: skip


@pytest.fixture(scope="module")
def replayed(tmp_path_factory) -> dict[str, Path]:
    """``groundstation replay LOG --out DIR`` once per bundled log."""
    out = {}
    for log in LOGS:
        d = tmp_path_factory.mktemp(log.stem)
        r = gs("replay", str(log), "--out", str(d), "--quiet", "--snapshots", "1")
        assert r.returncode == 0, r.stderr[-3000:]
        out[log.stem] = d
    return out


def decode_foxglove(path: Path) -> dict[str, Counter]:
    """Every protobuf message of ``path`` decoded twice: with the foxglove_schemas_protobuf class
    named by its schema, and with a class built from the schema data in the file."""
    counts: dict[str, Counter] = {}
    pools: dict[int, type] = {}
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            if channel.message_encoding != "protobuf":
                continue
            assert schema.encoding == "protobuf" and schema.name.startswith("foxglove."), schema
            name = schema.name.split(".", 1)[1]
            cls = getattr(importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2"), name)
            known = cls.FromString(message.data)
            if schema.id not in pools:
                pool = descriptor_pool.DescriptorPool()
                for f in FileDescriptorSet.FromString(schema.data).file:
                    pool.Add(f)
                pools[schema.id] = message_factory.GetMessageClass(
                    pool.FindMessageTypeByName(schema.name)
                )
            own = pools[schema.id].FromString(message.data)
            assert own.SerializeToString(deterministic=True) == known.SerializeToString(
                deterministic=True
            )
            counts.setdefault(channel.topic, Counter())[schema.name] += 1
    return counts


def event_states(path: Path) -> Counter:
    """``state`` metadata of the ``/detector/events`` Events of a recording."""
    from foxglove_schemas_protobuf.Event_pb2 import Event

    out: Counter = Counter()
    with open(path, "rb") as fh:
        for _s, _c, msg in make_reader(fh).iter_messages(topics=["/detector/events"]):
            meta = {m.key: m.value for m in Event.FromString(msg.data).metadata}
            out[meta.get("state")] += 1
    return out


def test_replay_outputs_of_every_bundled_log_decode_with_the_schema_library_alone(replayed):
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    assert len(LOGS) >= 3
    for stem, d in replayed.items():
        counts = decode_foxglove(d / "replay.mcap")
        for topic, schema in REQUIRED.items():
            assert counts.get(topic, {}).get(schema, 0) > 0, (stem, topic, counts.get(topic))
        report = json.loads((d / "report.json").read_text())
        states = event_states(d / "replay.mcap")
        assert states["contact"] == report["contacts"]  # one Event per contact event
        assert set(states) <= {"contact", "rejected"}
        assert counts["/detector/events"]["foxglove.Event"] == sum(states.values())
        with open(d / "replay.mcap", "rb") as fh:
            last = {}
            for _s, ch, msg in make_reader(fh).iter_messages(topics=["/map/mesh", "/map/contacts"]):
                last[ch.topic] = msg.data
        mesh = SceneUpdate.FromString(last["/map/mesh"]).entities[0]
        assert mesh.id == "mesh" and len(mesh.triangles[0].indices) > 0
        cloud = PointCloud.FromString(last["/map/contacts"])
        assert len(cloud.data) // cloud.point_stride > 0
        print(
            f"\n{stem}: " + ", ".join(f"{t} {sum(c.values())}" for t, c in sorted(counts.items()))
        )


def test_replay_mcap_is_a_station_recording_that_replays_again(replayed):
    from groundstation.acquisition.reader import open_recording
    from groundstation.openformats.export import check_groundstation_recording

    stem = "wall_slow_touch_gusts"
    with open_recording(ROOT / "replay_logs" / f"{stem}.mcap") as src:
        want = {t: n for t, n in src.topics().items() if t.startswith("raw.")}
        truth = src.truth()
    with open_recording(replayed[stem] / "replay.mcap") as out:
        check_groundstation_recording(out, need_raw=True)
        got = out.topics()
        assert out.truth() == truth
        assert out.metadata("groundstation.replay")["created_by"].startswith("groundstation replay")
    for topic, n in want.items():
        assert got[topic] == n, topic
    for topic in ("contact.event", "observations", "mapper.fit", "mesh"):
        assert got.get(topic, 0) > 0, topic
    from groundstation.acquisition.replay import iter_replay

    # its raw bytes decode to the samples the original decodes to (the first 5 s)
    a = [
        e.arrays["accel_mps2"].tobytes()
        for e in iter_replay(str(ROOT / "replay_logs" / f"{stem}.mcap"), end=5.0)
        if e.topic == "samples.imu"
    ]
    b = [e.arrays["accel_mps2"].tobytes() for e in iter_replay(
        str(replayed[stem] / "replay.mcap"), end=5.0) if e.topic == "samples.imu"]  # fmt: skip
    assert len(a) > 500 and a == b


def test_report_html_renders_offline_in_headless_chromium(replayed, tmp_path):
    from tests.support.browser import browser_page

    d = replayed["wall_survey"]
    html = (d / "report.html").read_text()
    assert "http://" not in html and "https://" not in html and "<script" not in html
    assert "trigger score" in html  # the default (impulse) detector's signal, named as such
    report = json.loads((d / "report.json").read_text())
    assert "touched surface missing" in html  # the truth scores next to what they cost
    assert ("phantom patch 1" in html) == bool(report["phantom_patches"])
    requests: list[str] = []
    with browser_page(1200, 900) as page:
        page.on("request", lambda req: requests.append(req.url))
        page.goto((d / "report.html").as_uri())
        page.wait_for_load_state("load")
        sizes = page.evaluate(
            "() => [...document.images].map(i => [i.id, i.naturalWidth, i.naturalHeight])"
        )
        rows = page.locator("#events ~ table tr").count() - 1
        truth_cells = page.locator("td.gust").count()
        png = tmp_path / "report.png"
        page.screenshot(path=str(png), full_page=True)
    assert {s[0] for s in sizes} == {"signal-plot", "map-views"}
    assert all(w > 500 and h > 200 for _, w, h in sizes), sizes
    assert rows == report["contacts"] and truth_cells >= 1
    assert all(u.startswith(("file:", "data:")) for u in requests), requests
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB"))
    assert img.shape[0] > 1500 and img.std() > 20  # a long page, not blank
    print(f"\nreport.html rendered to {img.shape[1]}x{img.shape[0]} px; {rows} event rows")


def test_detector_signal_crosses_the_trigger_at_every_event(tmp_path):
    """The signal channel is the score the impulse detector triggers on: it crosses 1 within
    every event the detector reported (so the channel shows why each event fired)."""
    from groundstation.config import load_config
    from groundstation.openformats.foxglove import FoxgloveTranslator
    from groundstation.pipeline.offline import run_offline

    cfg = load_config()
    tr = FoxgloveTranslator(cfg.contact, cfg.alignment, keep_signal=True)
    log = str(ROOT / "replay_logs/wall_slow_touch_gusts.mcap")
    res = run_offline(log, cfg, end=17.0, tap=tr.translate)
    tr.finish()
    t, g = (np.asarray(v) for v in zip(*tr.signal_series, strict=True))
    assert tr.signal.threshold_g == 1.0
    begins = {
        e.payload["id"]: e.header.source_ns for e in res.events if e.payload["state"] == "begin"
    }
    ended = [e for e in res.events if e.payload["state"] == "end"]
    assert len(ended) >= 5
    pad = 100_000_000  # the event's onset is found by walking back from the trigger
    inside = np.zeros(t.size, dtype=bool)
    for e in ended:
        sel = (t >= begins[e.payload["id"]] - pad) & (t <= e.header.source_ns + pad)
        inside |= sel
        assert g[sel].max() > 1.0
    # the same samples through the same detector: it opened every event the stage reported
    assert tr.signal.candidates >= len(ended)


def test_export_foxglove_adds_the_channels_to_an_old_recording(tmp_path):
    src = ROOT / "replay_logs" / "pillar_survey.mcap"
    out = tmp_path / "pillar_foxglove.mcap"
    r = gs("export", "foxglove", str(src), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "samples decoded from the raw bytes" in r.stdout
    counts = decode_foxglove(out)
    for topic in ("/vehicle/pose", "/tf", "/vehicle/trajectory", "/detector/signal", "/imu/gyro"):
        assert sum(counts[topic].values()) > 0, topic
    from groundstation.acquisition.reader import open_recording

    with open_recording(src) as a, open_recording(out) as b:
        for topic, n in a.topics().items():
            assert b.topics()[topic] == n, topic  # everything of the old file is kept
        assert b.truth() == a.truth()
    # exporting the export regenerates the Foxglove channels instead of doubling them
    again = tmp_path / "again.mcap"
    assert gs("export", "foxglove", str(out), "--out", str(again)).returncode == 0
    assert decode_foxglove(again) == counts
    bad = gs("export", "foxglove", str(out), "--out", str(out))
    assert bad.returncode == 2 and "is the input file" in bad.stderr


def test_replay_window_and_foreign_mcap(tmp_path):
    log = ROOT / "replay_logs" / "wall_survey.mcap"
    d = tmp_path / "window"
    r = gs("replay", str(log), "--start", "20", "--end", "35", "--out", str(d), "--quiet")
    assert r.returncode == 0, r.stderr[-2000:]
    report = json.loads((d / "report.json").read_text())
    assert report["duration_s"] == pytest.approx(15.0)
    from groundstation.acquisition.reader import open_recording

    with open_recording(log) as rec:
        t0 = rec.summary.start_ns
    with open_recording(d / "replay.mcap") as rec:
        raw = list(rec.messages("raw.mavlink"))
        events = [m.log_time_ns for m in rec.messages("contact.event")]
    assert (raw[0].log_time_ns - t0) / 1e9 >= 20.0 and (raw[-1].log_time_ns - t0) / 1e9 < 35.0
    assert all(20.0 <= (t - t0) / 1e9 < 35.0 for t in events)
    assert "20 s to 35 s" in (d / "report.html").read_text()

    assert gs("replay", str(log), "--start", "30", "--end", "10").returncode == 2
    late = gs("replay", str(log), "--start", "5000")
    assert late.returncode == 2 and "past the end" in late.stderr

    from mcap.writer import Writer

    foreign = tmp_path / "ros.mcap"
    with open(foreign, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        sid = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        cid = w.register_channel("/chatter", "cdr", sid)
        w.add_message(
            cid, log_time=1, data=b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00", publish_time=1
        )
        w.finish()
    r = gs("replay", str(foreign), "--out", str(tmp_path / "x"))
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "not a groundstation recording" in r.stderr and "/chatter (cdr)" in r.stderr
    assert "hint:" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "x" / "report.json").exists()
