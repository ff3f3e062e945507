"""Scripted pilots (pure, deterministic): what a pilot flies in a scene.

- ``hover``: holds the start position.
- ``survey``: touches every reachable face (:func:`~firmware_bridge.sitl.planner.plan_survey`)
  straight in along the normal at 1 m/s.
- ``touch``, ``slow_touch``: one touch at 1 m/s; a 0.1 m/s touch then a 1 m/s one.
- ``varied``: the survey's touches with what real pilots do: each touch draws its normal
  approach speed (0.2-1.2 m/s), its angle off the normal (0-45 deg, in a random direction of the
  face plane, with the longest clear run-up) and a pause at the standoff from the seed.
- ``free``: no touches at all: fast legs in clear space (3-5 m/s), hard braking (0.8-2 G) and
  turns at speed (0.8-1.8 G), as real pilots do at the end of a path
  (:mod:`~firmware_bridge.sitl.maneuvers`).

A pilot maps (sim time, body state) to a :class:`~firmware_bridge.sitl.control.Setpoint`; the
``varied`` and ``free`` pilots draw from their own generator (seeded from the simulation's seed),
so the other pilots and every other random stream are unchanged by them.
"""

from __future__ import annotations

import math

import numpy as np

from firmware_bridge.errors import BridgeError
from firmware_bridge.sitl.control import Setpoint
from firmware_bridge.sitl.maneuvers import DashRun, ManeuverLog, plan_dashes
from firmware_bridge.sitl.planner import (  # noqa: F401 - re-exported: pilots' public names
    Planner,
    TouchTarget,
    _dist,
    plan_survey,
)
from firmware_bridge.sitl.scene import Scene

Vec = tuple[float, float, float]
PILOTS = ("hover", "survey", "touch", "slow_touch", "varied", "free")


class PilotError(BridgeError, ValueError):
    """An unknown pilot name or a scene in which the pilot cannot fly."""


class ScriptPilot:
    """Flies a list of actions: ``("goto", point, speed)``, ``("touch", TouchTarget, speed)``,
    ``("hover", seconds)``, ``("dash", Dash)``. ``done`` turns True after the last action.

    ``body`` is any :class:`~firmware_bridge.sitl.engine.Physics` (position, velocity, contact).
    ``maneuvers`` records the dashes' accelerate / turn / brake intervals.
    """

    def __init__(
        self,
        scene: Scene,
        actions: list[tuple],
        yaw: float = 0.0,
        planner: Planner | None = None,
    ):
        self.scene = scene
        self.actions = list(actions)
        self.planner = planner  # set: re-route a goto when pushed off its line (gusts)
        self._check = 0.0
        self._away: Vec = (0.0, 0.0, 1.0)  # backoff direction after a touch
        self.yaw = yaw
        self.i = 0
        self.phase = "start"
        self.t0 = 0.0
        self.hold: Vec = scene.start
        self.touched: list[tuple[int, str]] = []  # faces where contact was made, in order
        self.maneuvers = ManeuverLog()
        self._dash: DashRun | None = None
        self.done = not actions

    def _next(self, t: float, body) -> None:
        self.i += 1
        self.phase, self.t0 = "start", t
        self.hold = body.position
        if self.i >= len(self.actions):
            self.done = True

    def _reroute(self, pos: Vec, target: Vec, speed: float) -> bool:
        """If a gust pushed the vehicle > 0.25 m off the straight line of the current goto and
        the way on to ``target`` is blocked, replace the goto by a planned path."""
        a = self.hold
        ab = (target[0] - a[0], target[1] - a[1], target[2] - a[2])
        ap = (pos[0] - a[0], pos[1] - a[1], pos[2] - a[2])
        L2 = ab[0] ** 2 + ab[1] ** 2 + ab[2] ** 2
        u = (
            0.0
            if L2 == 0
            else max(0.0, min(1.0, (ap[0] * ab[0] + ap[1] * ab[1] + ap[2] * ab[2]) / L2))
        )
        off = math.dist(pos, (a[0] + u * ab[0], a[1] + u * ab[1], a[2] + u * ab[2]))
        planner = self.planner
        if off < 0.25 or planner is None or planner.segment_free(pos, target, margin=0.05):
            return False
        path = planner.path(pos, target)
        if not path:
            return False
        self.actions[self.i : self.i + 1] = [("goto", w, speed) for w in path]
        self.hold = pos  # the new line starts here
        return True

    def setpoint(self, t: float, body) -> Setpoint:
        """Setpoint for time ``t`` (s) given the body's true state."""
        if self.done:
            return Setpoint(position=self.hold, yaw=self.yaw)
        act = self.actions[self.i]
        if self.phase == "start":
            self.phase, self.t0 = "run", t
        kind = act[0]
        pos, vel = body.position, body.velocity
        if kind == "hover":
            if t - self.t0 >= act[1]:
                self._next(t, body)
            return Setpoint(position=self.hold, yaw=self.yaw)
        if kind == "goto":
            target, speed = act[1], act[2]
            if self.planner is not None and t >= self._check:
                self._check = t + 0.1
                if self._reroute(pos, target, speed):
                    target, self.t0 = self.actions[self.i][1], t
            arrived = _dist(pos, target) < 0.08 and math.hypot(*vel) < 0.15
            if arrived or t - self.t0 > _dist(self.hold, target) / speed + 8.0:
                self._next(t, body)
            return Setpoint(position=target, yaw=self.yaw, max_speed=speed)
        if kind == "dash":
            if self._dash is None:
                self._dash = DashRun(act[1], self.maneuvers, self.yaw)
            sp = self._dash.setpoint(t, pos, vel)
            if sp is not None:
                return sp
            self._dash = None
            self._next(t, body)
            return Setpoint(position=self.hold, yaw=self.yaw)
        # touch: fly along -n (or the target's direction) at speed until contact, then back off.
        tgt: TouchTarget = act[1]
        speed = act[2]  # a 4th element marks a retried touch
        n = tgt.normal
        if self.phase == "run":
            c = body.contact
            run_up = 0.6 if tgt.direction is None else _dist(tgt.standoff, tgt.centre)
            self._away = n
            if c is not None and c.object_index == tgt.face[0]:
                self.touched.append(tgt.face)
                self.phase, self.t0 = "backoff", t
            elif t - self.t0 > run_up / speed + 3.0:
                self.phase, self.t0 = "backoff", t
            elif self.planner is not None and c is not None and c.object_index >= 0:
                self.phase, self.t0, self._away = "backoff", t, c.normal  # hit something else
            e = (tgt.centre[0] - pos[0], tgt.centre[1] - pos[1], tgt.centre[2] - pos[2])
            if tgt.direction is not None:  # along d through C: v = d s + k (e - (e.d) d)
                d = tgt.direction
                ed = e[0] * d[0] + e[1] * d[1] + e[2] * d[2]
                off = tuple(e[i] - ed * d[i] for i in range(3))
                if self.phase == "run" and math.hypot(*off) > 0.25 and self._retry(act, pos):
                    return Setpoint(position=pos, yaw=self.yaw)  # pushed off the line: re-fly
                v = tuple(d[i] * speed + 2.0 * off[i] for i in range(3))
                return Setpoint(velocity=v, yaw=self.yaw, max_speed=max(speed, 1.5))  # type: ignore
            en = e[0] * n[0] + e[1] * n[1] + e[2] * n[2]
            k = 2.0  # hold the line through C perpendicular to n
            v = tuple(-n[i] * speed + k * (e[i] - en * n[i]) for i in range(3))
            return Setpoint(velocity=v, yaw=self.yaw, max_speed=max(speed, 1.5))  # type: ignore
        if t - self.t0 < 0.4:
            n = self._away
            return Setpoint(velocity=(0.5 * n[0], 0.5 * n[1], 0.5 * n[2]), yaw=self.yaw)
        self._next(t, body)
        return Setpoint(position=tgt.standoff, yaw=self.yaw)

    def _retry(self, act: tuple, pos: Vec) -> bool:
        """A gust pushed the vehicle off a touch's line: fly back to the standoff on a planned
        path and touch again (once); False for pilots without a planner or a second time."""
        if self.planner is None or len(act) > 3:
            return False
        tgt = act[1]
        path = self.planner.path(pos, tgt.standoff) or [tgt.standoff]
        again = [("goto", w, 1.0) for w in path] + [("hover", 0.3), (*act, "retry")]
        self.actions[self.i : self.i + 1] = again
        self.phase, self.hold = "start", pos
        return True


def _touch_actions(
    planner: Planner, here: Vec, tgt: TouchTarget, speed: float, transit: float = 1.0
) -> list[tuple]:
    path = planner.path(here, tgt.standoff) or [tgt.standoff]
    acts: list[tuple] = [("goto", w, transit) for w in path]
    acts += [("hover", 0.3), ("touch", tgt, speed), ("goto", tgt.standoff, transit)]
    return acts


def _varied_actions(
    planner: Planner, targets: list[TouchTarget], rng: np.random.Generator
) -> tuple[list[tuple], Vec]:
    """The survey's touches, each with a drawn speed, angle, pause and transit speed."""
    acts: list[tuple] = []
    here = planner.scene.start
    for tgt in targets:
        v_normal = float(rng.uniform(0.2, 1.2))  # m/s along the normal
        angle = float(rng.uniform(0.0, math.radians(45.0)))
        azimuth = float(rng.uniform(0.0, 2 * math.pi))
        pause = float(rng.uniform(0.3, 2.0))
        transit = float(rng.uniform(0.6, 1.5))
        run_ups = (0.8, 0.7, 0.6, 0.5, 0.45, 0.4, 0.35)
        aimed = None
        for k in range(4):  # other directions in the face plane, then straight in
            aimed = planner.angled(tgt, angle, azimuth + k * math.pi / 2, run_ups)
            if aimed is not None:
                break
        if aimed is None:
            aimed, angle = planner.angled(tgt, 0.0, 0.0, run_ups) or tgt, 0.0
        speed = v_normal / math.cos(angle)
        path = planner.path(here, aimed.standoff) or [aimed.standoff]
        acts += [("goto", w, transit) for w in path]
        acts += [("hover", pause), ("touch", aimed, speed), ("goto", aimed.standoff, transit)]
        here = aimed.standoff
    return acts, here


def _free_actions(
    planner: Planner, rng: np.random.Generator, legs: int = 8
) -> tuple[list[tuple], Vec]:
    """Fast legs with hard braking and turns, joined by collision-free transits."""
    dashes = plan_dashes(planner, rng, legs)
    acts: list[tuple] = []
    here = planner.scene.start
    for dash in dashes:
        start, end = dash.points[0], dash.points[-1]
        acts += [("goto", w, 1.2) for w in planner.path(here, start) or [start]]
        acts += [("hover", float(rng.uniform(0.3, 1.0))), ("dash", dash)]
        # Back onto the planned end along the (clear) leg, wherever the braking stopped.
        acts += [("hover", float(rng.uniform(0.5, 1.5))), ("goto", end, 1.0)]
        here = end
    return acts, here


def make_pilot(name: str, scene: Scene, radius: float, height: float, seed: int = 0) -> ScriptPilot:
    """Build the scripted pilot ``name`` (one of :data:`PILOTS`).

    ``radius`` and ``height`` (m) are the planning cylinder around the drone; ``seed`` feeds
    the ``varied`` and ``free`` pilots' own generator.
    """
    planner = Planner(scene, radius, height)
    if name == "hover":
        return ScriptPilot(scene, [])
    if name not in PILOTS:
        raise PilotError(f"unknown pilot script {name!r}", hint=f"use {', '.join(PILOTS)}")
    rng = np.random.default_rng([seed, 2])  # the pilot's own stream (mocap noise uses [seed, 1])
    acts: list[tuple] = [("hover", 1.0)]
    if name == "free":
        more, here = _free_actions(planner, rng)
        if not any(a[0] == "dash" for a in more):
            raise PilotError(
                f"pilot 'free': no clear straight leg of >= 2.5 m in scene {scene.name!r}",
                hint="the free pilot needs open space inside the region to fly fast",
            )
        acts += more
        acts += [("goto", w, 1.2) for w in planner.path(here, scene.start) or [scene.start]]
        acts.append(("hover", 1.0))
        return ScriptPilot(scene, acts, planner=planner)
    targets = plan_survey(scene, radius, height)
    if not targets:
        raise PilotError(
            f"pilot {name!r}: no reachable face in scene {scene.name!r}",
            hint="leave >= 0.6 m of free space in front of a face inside the region",
        )
    here = scene.start
    if name == "survey":
        for tgt in targets:
            acts += _touch_actions(planner, here, tgt, 1.0)
            here = tgt.standoff
    elif name == "varied":
        more, here = _varied_actions(planner, targets, rng)
        acts += more
    elif name == "touch":
        acts += _touch_actions(planner, here, targets[0], 1.0)
        here = targets[0].standoff
    else:  # slow_touch
        acts += _touch_actions(planner, here, targets[0], 0.1)
        acts += [("hover", 1.0), ("touch", targets[0], 1.0), ("goto", targets[0].standoff, 1.0)]
        here = targets[0].standoff
    acts += [("goto", w, 1.0) for w in planner.path(here, scene.start) or [scene.start]]
    acts.append(("hover", 1.0))
    # The new pilots re-route after gusts; the old ones fly as they always did (same bytes).
    return ScriptPilot(scene, acts, planner=planner if name == "varied" else None)
