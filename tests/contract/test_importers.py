"""Importers on the real files in external_data: counts, units, frames, wire validity,
determinism, and the tlog export -> import round trip."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_bridge.frames import rotate
from firmware_bridge.mavlink.codec import MavlinkCodec
from firmware_bridge.mavlink.messages import AttitudeSample, ImuSample, MocapPose
from firmware_bridge.natnet import FrameOfData, parse_packet
from groundstation.acquisition import layout
from groundstation.acquisition.importers import FlightStreams, ImportDataError
from groundstation.acquisition.importers.csv_imu import (
    IMU_COLUMNS,
    convert_xsens,
    estimate_lag,
    import_csv,
    read_numeric_csv,
)
from groundstation.acquisition.importers.export_tlog import export_tlog
from groundstation.acquisition.importers.tlog import import_tlog
from groundstation.acquisition.importers.ulog import import_ulog
from groundstation.acquisition.reader import open_recording

pytestmark = pytest.mark.external

PATHS = ["Horizontal/path_1", "Horizontal/path_4", "Vertical/path_1"]
ULOGS = ["sample.ulg", "sample_px4_events.ulg"]


def decode_recording(path):
    """Decode every raw channel through the live decoders; returns records and codec stats."""
    codecs: dict[int, MavlinkCodec] = {}
    imu, att, pose, natnet = [], [], [], []
    with open_recording(path) as rec:
        assert not rec.truncated
        for m in rec.messages():
            if m.topic == layout.RAW_MAVLINK_TOPIC:
                codec = codecs.setdefault(m.channel.id, MavlinkCodec())
                for r in codec.decode(m.data, m.log_time_ns):
                    {ImuSample: imu, AttitudeSample: att, MocapPose: pose}[type(r)].append(r)
            elif m.topic == layout.RAW_NATNET_TOPIC:
                version = tuple(int(v) for v in m.channel.metadata["natnet_version"].split("."))
                frame = parse_packet(m.data, version)
                assert isinstance(frame, FrameOfData)
                natnet.append((m.log_time_ns, frame))
    crc = sum(c.stats.crc_errors for c in codecs.values())
    garbage = sum(c.stats.garbage_bytes for c in codecs.values())
    return imu, att, pose, natnet, crc, garbage


def check_streams(imu, att):
    t_imu = np.array([r.time_source_ns for r in imu])
    t_att = np.array([r.time_source_ns for r in att])
    assert np.all(np.diff(t_imu) > 0) and np.all(np.diff(t_att) > 0)
    q = np.array([r.quaternion for r in att])
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-5)
    return t_imu, t_att, np.array([r.accel for r in imu]), q


@pytest.mark.parametrize("flight", PATHS)
def test_csv_import_is_replayable_with_explicit_units_and_frames(external_data, tmp_path, flight):
    src = external_data / "aggressive_flight" / flight / "IMU_1.csv"
    n_rows = sum(1 for _ in open(src)) - 1
    out = tmp_path / "flight.mcap"
    report = import_csv(src, out)
    assert report.counts["imu (HIGHRES_IMU)"] == n_rows
    assert report.counts["attitude (ATTITUDE_QUATERNION)"] == n_rows
    assert report.duration_s == pytest.approx(n_rows / 120.0, rel=0.01)
    assert report.rates_hz()["imu (HIGHRES_IMU)"] == pytest.approx(120.0, rel=0.01)
    assert report.counts["pose (NatNet 4.1)"] > 150  # GT.csv at 10 Hz, aligned
    imu, att, _, natnet, crc, garbage = decode_recording(out)
    assert crc == 0 and garbage == 0
    assert len(imu) == len(att) == n_rows and len(natnet) == report.counts["pose (NatNet 4.1)"]
    t_imu, t_att, acc, q = check_streams(imu, att)
    # Units: the specific force averages ~1 g over the flight, and points up (-z in FRD).
    assert 9.0 < np.linalg.norm(acc, axis=1).mean() < 12.0
    assert acc[:, 2].mean() < -8.0
    # Frames: rotated to NED by the imported attitude, the flight-mean specific force is
    # (0, 0, -g): a periodic path has zero mean acceleration.
    q_at_imu = q[np.searchsorted(t_att, t_imu, side="right") - 1]
    f_ned = rotate(q_at_imu, acc).mean(axis=0)
    assert abs(f_ned[0]) < 0.5 and abs(f_ned[1]) < 0.5 and f_ned[2] == pytest.approx(-9.75, abs=0.3)
    with open_recording(out) as rec:
        truth = rec.truth()
        meta = rec.metadata()
    assert truth["contact_free"] is True and truth["contacts"] == []
    assert "Hurwitz" in truth["attribution"] and str(src) in meta["sources"]


def test_csv_conversion_conventions_on_synthetic_samples():
    # Level, facing ENU east (yaw 0): in NED that is a heading of +90 deg; gravity up on S z.
    cols = {
        "time": np.array([0.0, 1 / 120]),
        "Euler_X": np.array([0.0, 30.0]),
        "Euler_Y": np.array([0.0, -20.0]),
        "Euler_Z": np.array([0.0, 45.0]),
        "Acc_X": np.zeros(2),
        "Acc_Y": np.zeros(2),
        "Acc_Z": np.array([9.81, 9.81]),
        "Gyr_X": np.array([90.0, 0.0]),
        "Gyr_Y": np.array([0.0, 90.0]),
        "Gyr_Z": np.array([0.0, 0.0]),
    }
    s = convert_xsens(cols)
    assert np.allclose(s.accel_frd[0], [0, 0, -9.81])
    assert np.allclose(s.gyro_frd[0], [np.pi / 2, 0, 0]) and np.allclose(
        s.gyro_frd[1], [0, -np.pi / 2, 0]
    )
    assert np.allclose(rotate(s.q_ned_frd[0], [1, 0, 0]), [0, 1, 0], atol=1e-12)  # nose east
    # Tilted sample: a specific force equal to gravity-up in the sensor frame must map to
    # (0, 0, -g) in NED through the converted attitude.
    phi, th = np.radians(30.0), np.radians(-20.0)
    f_s = 9.81 * np.array([-np.sin(th), np.sin(phi) * np.cos(th), np.cos(phi) * np.cos(th)])
    f_frd = f_s * [1, -1, -1]
    assert np.allclose(rotate(s.q_ned_frd[1], f_frd), [0, 0, -9.81], atol=1e-9)
    assert s.imu_t_ns.tolist() == [0, 8_333_333]


def test_lag_estimate_recovers_a_known_shift():
    t = np.arange(0, 20, 1 / 120)
    x = np.sin(1.3 * t) + 0.3 * np.sin(4.1 * t)
    t_gt = np.arange(0, 18, 0.1)
    lag, corr = estimate_lag(t, x, t_gt, np.interp(t_gt + 0.68, t, x))
    assert lag == pytest.approx(0.68, abs=0.011) and corr > 0.999


def test_bad_csv_rows_are_skipped_and_counted(tmp_path):
    header = "time,Euler_X,Euler_Y,Euler_Z,Acc_X,Acc_Y,Acc_Z,Gyr_X,Gyr_Y,Gyr_Z\n"
    good = "{t},0,0,0,0,0,9.8,0,0,0\n"
    text = header + good.format(t=0) + "0.01,x,0,0,0,0,9.8,0,0,0\n" + "0.02,0,0\n"
    text += "0.03,nan,0,0,0,0,9.8,0,0,0\n" + good.format(t=0.04) + good.format(t=0.04)
    p = tmp_path / "imu.csv"
    p.write_text(text)
    from collections import Counter

    skipped = Counter()
    cols = read_numeric_csv(p, IMU_COLUMNS, skipped)
    assert cols["time"].tolist() == [0.0, 0.04]
    assert sum(skipped.values()) == 4 and len(skipped) == 4
    with pytest.raises(ImportDataError, match="lacks column"):
        read_numeric_csv(p, ("time", "Mag_X"), Counter())


def test_streams_validation_names_the_problem():
    s = FlightStreams(
        imu_t_ns=np.array([0, 0]),
        accel_frd=np.zeros((2, 3)),
        gyro_frd=np.zeros((2, 3)),
        att_t_ns=np.zeros(0, np.int64),
        q_ned_frd=np.zeros((0, 4)),
        rates_frd=np.zeros((0, 3)),
    )
    with pytest.raises(ImportDataError, match="imu times"):
        s.validate()


@pytest.mark.parametrize("name", ULOGS)
def test_ulog_import_is_replayable_and_exact(external_data, tmp_path, name):
    from pyulog import ULog

    src = external_data / "px4_ulog" / name
    out = tmp_path / "ulog.mcap"
    report = import_ulog(src, out)
    ulog = ULog(str(src), ["sensor_combined"])
    sc = ulog.get_dataset("sensor_combined").data
    assert report.counts["imu (HIGHRES_IMU)"] == len(sc["timestamp"])
    imu, att, _, natnet, crc, garbage = decode_recording(out)
    assert crc == 0 and garbage == 0
    assert (
        len(imu) == len(sc["timestamp"])
        and len(att) == report.counts["attitude (ATTITUDE_QUATERNION)"]
    )
    t_imu, _, acc, _ = check_streams(imu, att)
    # Values are the ULog's own (float32 on both sides), times keep their spacing in us.
    src_acc = np.stack([sc[f"accelerometer_m_s2[{i}]"] for i in range(3)], axis=1)
    assert np.array_equal(acc.astype(np.float32), src_acc.astype(np.float32))
    assert np.array_equal(np.diff(t_imu) // 1000, np.diff(sc["timestamp"].astype(np.int64)))
    assert 9.0 < np.linalg.norm(acc, axis=1).mean() < 10.6
    if name == "sample_px4_events.ulg":
        assert report.counts["pose (NatNet 4.1)"] == len(natnet) > 100
        assert report.rates_hz()["imu (HIGHRES_IMU)"] == pytest.approx(250.0, rel=0.02)
    else:
        assert "pose (NatNet 4.1)" not in report.counts  # bench log: positions never valid
        assert report.skipped["vehicle_local_position: xy/z not valid"] > 0


def test_ulog_positions_survive_the_natnet_encoding(external_data, tmp_path):
    from firmware_bridge.frames import enu_to_ned, motive_to_world
    from groundstation.acquisition.importers.ulog import convert_ulog

    src = external_data / "px4_ulog" / "sample_px4_events.ulg"
    streams = convert_ulog(src)
    import_ulog(src, tmp_path / "u.mcap")
    _, _, _, natnet, _, _ = decode_recording(tmp_path / "u.mcap")
    p = np.array([f.rigid_bodies[0].position for _, f in natnet])
    q = np.array([f.rigid_bodies[0].orientation for _, f in natnet])
    p_w, _ = motive_to_world(p, q)
    assert np.allclose(enu_to_ned(p_w), streams.pos_ned, atol=1e-5)  # float32 on the wire
    assert [t for t, _ in natnet] == streams.pose_t_ns.tolist()


def test_import_is_deterministic(external_data, tmp_path):
    src = external_data / "aggressive_flight" / "Horizontal" / "path_4" / "IMU_1.csv"
    import_csv(src, tmp_path / "a.mcap")
    import_csv(src, tmp_path / "b.mcap")
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()
    a = decode_recording(tmp_path / "a.mcap")
    b = decode_recording(tmp_path / "b.mcap")
    assert a[0] == b[0] and a[1] == b[1]


def test_tlog_export_import_round_trip(external_data, tmp_path):
    src = external_data / "aggressive_flight" / "Horizontal" / "path_1" / "IMU_1.csv"
    first = tmp_path / "first.mcap"
    rep = import_csv(src, first)
    # utc_offset_ns=0: undated log times, so the round trip keeps the receive times exactly
    # (by default the records are dated with a wall clock, issue 15)
    exported = export_tlog(first, tmp_path / "f.tlog", utc_offset_ns=0)
    n_pose = rep.counts["pose (NatNet 4.1)"]
    assert exported.counts["ATT_POS_MOCAP (from NatNet)"] == n_pose
    back = import_tlog(tmp_path / "f.tlog", tmp_path / "second.mcap")
    assert back.counts["HIGHRES_IMU"] == rep.counts["imu (HIGHRES_IMU)"]
    assert back.counts["ATT_POS_MOCAP"] == n_pose and not back.skipped
    imu1, att1, _, natnet, _, _ = decode_recording(first)
    imu2, att2, pose2, _, crc, _ = decode_recording(tmp_path / "second.mcap")
    assert crc == 0
    assert imu1 == imu2 and att1 == att2  # same records, same receive times
    with open_recording(first) as a, open_recording(tmp_path / "second.mcap") as b:
        raw1 = [m.data for m in a.messages("raw.mavlink")]
        raw2 = [m.data for m in b.messages("raw.mavlink") if m.data[7] != 138]
    assert raw1 == raw2  # wire bytes identical through the tlog
    # Mocap poses: NatNet (float32, Motive frame) -> ATT_POS_MOCAP (NED) keeps the position.
    from firmware_bridge.frames import enu_to_ned, motive_to_world

    p_w, _ = motive_to_world(
        [f.rigid_bodies[0].position for _, f in natnet],
        [f.rigid_bodies[0].orientation for _, f in natnet],
    )
    assert np.allclose([r.position for r in pose2], enu_to_ned(p_w), atol=1e-5)


def test_damaged_tlog_is_skipped_and_counted(external_data, tmp_path):
    src = external_data / "aggressive_flight" / "Vertical" / "path_1" / "IMU_1.csv"
    import_csv(src, tmp_path / "a.mcap", pose_transport="mavlink")
    export_tlog(tmp_path / "a.mcap", tmp_path / "a.tlog")
    data = bytearray((tmp_path / "a.tlog").read_bytes())
    full = import_tlog(tmp_path / "a.tlog", tmp_path / "full.mcap")
    data[10_000:10_004] = b"\x00\x00\x00\x00"
    (tmp_path / "bad.tlog").write_bytes(bytes(data[:-5]))
    rep = import_tlog(tmp_path / "bad.tlog", tmp_path / "bad.mcap")
    lost = sum(full.counts.values()) - sum(rep.counts.values())
    assert 1 <= lost <= 3
    assert rep.skipped["truncated record at end of file"] == 1
    assert rep.skipped["damaged record (bad frame), resynced"] >= 1
    *_, crc, _ = decode_recording(tmp_path / "bad.mcap")
    assert crc == 0


def test_missing_and_garbage_inputs_are_clear_errors(tmp_path):
    with pytest.raises(ImportDataError, match="does not exist"):
        import_csv(tmp_path / "nope.csv", tmp_path / "o.mcap")
    (tmp_path / "junk.ulg").write_bytes(b"definitely not a ulog")
    with pytest.raises(ImportDataError, match="ULog"):
        import_ulog(tmp_path / "junk.ulg", tmp_path / "o.mcap")
    (tmp_path / "junk.tlog").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ImportDataError, match="no valid MAVLink"):
        import_tlog(tmp_path / "junk.tlog", tmp_path / "o.mcap")


def test_commands_through_the_cli(external_data, tmp_path, capsys):
    from groundstation import cli

    src = external_data / "px4_ulog" / "sample_px4_events.ulg"
    assert cli.main(["import", "ulog", str(src), "--out", str(tmp_path / "u.mcap")]) == 0
    assert "HIGHRES_IMU" in capsys.readouterr().out
    tlog = tmp_path / "u.tlog"
    assert cli.main(["export", "tlog", str(tmp_path / "u.mcap"), "--out", str(tlog)]) == 0
    assert cli.main(["import", "tlog", str(tlog), "--out", str(tmp_path / "t.mcap")]) == 0
    assert "ATT_POS_MOCAP" in capsys.readouterr().out
    csv = external_data / "aggressive_flight" / "Vertical" / "path_1" / "IMU_avg.csv"
    out = tmp_path / "c.mcap"
    assert cli.main(["import", "csv", str(csv), "--out", str(out), "--pose", "mavlink"]) == 0
    with open_recording(out) as rec:
        assert rec.metadata()["created_by"].startswith("groundstation import csv")
        assert set(rec.topics()) == {"raw.mavlink"}  # poses as ATT_POS_MOCAP
        sources = {c.metadata["source"] for c in rec.summary.channels}
    assert len(sources) == 2  # autopilot link and mocap sender are separate channels
    _, _, pose, _, crc, _ = decode_recording(out)
    assert crc == 0 and len(pose) > 100
    # errors are reported, not raised
    assert cli.main(["import", "csv", str(tmp_path / "nope.csv"), "--out", str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err
    bad_out = tmp_path / "no-such-dir" / "x.mcap"
    assert cli.main(["import", "ulog", str(src), "--out", str(bad_out)]) == 2
    assert "no-such-dir" in capsys.readouterr().err
