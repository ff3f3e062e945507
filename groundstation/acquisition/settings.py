"""Settings of the acquisition processes and decoders (the ``[acquisition]`` section)."""

from __future__ import annotations

import dataclasses
from typing import Literal

from groundstation.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class AcquisitionSettings:
    """Settings of the acquisition processes and decoders (units in the names).

    Attributes
    ----------
    imu_rate_hz, attitude_rate_hz : float
        Rates requested with MAV_CMD_SET_MESSAGE_INTERVAL for HIGHRES_IMU / ATTITUDE_QUATERNION.
    timesync_period_s : float
        Period of the station's TIMESYNC pings.
    health_period_s : float
        Period of ``link.health`` and ``status`` messages (replay: of log time).
    timesync_window : int
        Minimum-RTT window of the TIMESYNC filter (``TimesyncEstimator``).
    timesync_max_rtt_ms : float
        Round trips longer than this are rejected.
    mocap_latency_ms : float
        Mocap pipeline latency subtracted from the pose receive time (``t_station_ns``).
    natnet_version : str
        NatNet bitstream version, "3.0" .. "4.1" (a recording's channel metadata wins on replay).
    motive_up : {"y", "z"}
        Motive up axis.
    quaternion_order : {"xyzw", "wxyz"}
        Order of incoming mocap quaternions (NatNet: "xyzw").
    system_id, component_id : int
        The station's MAVLink address.
    target_system : int
        Vehicle system id for MANUAL_CONTROL and commands.
    subscriber_timeout_s : float
        How long a publisher waits for its subscribers before it starts anyway (with a warning).
    replay_flow_window : int
        Credit window of the replay source at speed=max (messages per topic).
    link_allow_peers : tuple of str
        UDP firmware links: the only senders accepted ("HOST" or "HOST:PORT"). Empty: lock to the
        first vehicle heard (its address and system id); others are counted and ignored.
    vehicle_system_id : int
        UDP firmware links: lock only to this MAVLink system id (0 = the first one heard).
    signing_key_file : str
        MAVLink 2 signing key (32 raw bytes or 64 hex characters) for the command uplink: every
        frame the station sends is signed with it. Empty: no signing (``live --signing-key``).
    """

    imu_rate_hz: float = 200.0
    attitude_rate_hz: float = 200.0
    timesync_period_s: float = 1.0
    health_period_s: float = 1.0
    timesync_window: int = 16
    timesync_max_rtt_ms: float = 500.0
    mocap_latency_ms: float = 0.0
    natnet_version: str = "4.1"
    motive_up: Literal["y", "z"] = "y"
    quaternion_order: Literal["xyzw", "wxyz"] = "xyzw"
    system_id: int = 255
    component_id: int = 190
    target_system: int = 1
    subscriber_timeout_s: float = 20.0
    replay_flow_window: int = 256
    link_allow_peers: tuple[str, ...] = ()
    vehicle_system_id: int = 0
    signing_key_file: str = ""

    def __post_init__(self) -> None:
        for name in ("imu_rate_hz", "attitude_rate_hz", "timesync_period_s", "health_period_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"acquisition.{name}={getattr(self, name)!r} must be > 0")
        if self.mocap_latency_ms < 0:
            raise ConfigError(f"acquisition.mocap_latency_ms={self.mocap_latency_ms} must be >= 0")
        natnet_version_tuple(self.natnet_version)
        if self.timesync_window < 1 or self.replay_flow_window < 1:
            raise ConfigError("acquisition.timesync_window and replay_flow_window must be >= 1")
        if not 0 <= self.vehicle_system_id <= 255:
            raise ConfigError(
                f"acquisition.vehicle_system_id={self.vehicle_system_id} must be in 0..255 "
                "(0 = lock to the first vehicle heard)"
            )
        from firmware_bridge.errors import UriError
        from firmware_bridge.link.peer import parse_peer

        for peer in self.link_allow_peers:
            try:
                parse_peer(peer)
            except UriError as exc:
                raise ConfigError(
                    f"acquisition.link_allow_peers: {exc.message}", exc.hint
                ) from None

    @property
    def natnet_version_tuple(self) -> tuple[int, int]:
        return natnet_version_tuple(self.natnet_version)


def natnet_version_tuple(text: str) -> tuple[int, int]:
    """``"4.1"`` -> ``(4, 1)``; raises :class:`ConfigError` naming the bad value."""
    try:
        major, minor = (int(p) for p in str(text).split("."))
    except ValueError:
        raise ConfigError(
            f"natnet_version {text!r} is not MAJOR.MINOR", hint="e.g. 4.1 (Motive 3.x)"
        ) from None
    return major, minor
