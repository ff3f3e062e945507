"""Evidence per candidate impulse: named physical features and a calibrated ``p_false`` (pure).

A touch and a gust leave different traces (issue 12, DESIGN.md §7):

- a touch is **short** (the guard and the structure stop the drone in 20-40 ms), a gust lasts
  50-300 ms (``duration_s``);
- before a touch the drone **approaches** the contact point (its velocity along the outward
  normal is negative, ``approach_mps`` > 0) and after it it **rebounds** (positive,
  ``rebound_mps`` > 0: the normal velocity reverses within 50-150 ms); a gust pushes the drone
  along its direction whether it was moving that way or not;
- a touch's impulse follows from the approach speed (``dv = (1 + e) v`` with a restitution
  ``e`` of 0.2-0.7), a gust's does not (``log_dv_per_approach``);
- a real external force moves the drone: the mocap velocity change across the impulse agrees
  with the impulse the IMU measured (``agreement`` ~ 1), while vibration bursts and sensor
  glitches integrate to little and move nothing;
- across the thrust axis the accelerometer sees external forces alone (``axial_fraction``:
  0 for a force across the thrust axis, 1 along it, where thrust changes also live);
- a multirotor changes its own horizontal acceleration by tilting, so a commanded brake or
  turn **rotates the vehicle before** the deceleration the accelerometer sees, while a touch
  comes to a vehicle flying steadily (``turn_rate_radps``: the mean angular speed over the
  window before the onset, from the attitude; no mocap needed).

:class:`EvidenceModel` combines them in a logistic model on those named features (one with
mocap, one from the IMU alone for logs without poses; of degree 1, or 2 with their products
two by two, :func:`design`), fitted on labelled SITL flights by
``groundstation bench detector --train`` and shipped as ``evidence_model.json`` beside this
module (its ``provenance`` says which flights and seeds). ``p_false`` is calibrated for a
mix of touches and false impulses as in those flights (about one to one).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from groundstation.errors import ConfigError

BUNDLED_MODEL = Path(__file__).with_name("evidence_model.json")
#: ``turn_rate_radps`` below the floor is steady flight, above the cap a manoeuvre however fast.
#: The SITL's touches come at 0.06 rad/s (median; q90 0.15), its braking false alarms at 2.2
#: (q10 1.25). A real airframe wobbles more: the DJI of ``aggressive_flight`` (real gyro, 120 Hz)
#: turns faster than 0.15 rad/s in nine 100 ms windows out of ten, so the floor sits well above
#: the SITL's calm, and a touch from a real vehicle's steady flight reads as steady.
TURN_RATE_FLOOR_RADPS = 0.3
TURN_RATE_CAP_RADPS = 3.0


@dataclasses.dataclass(frozen=True)
class ImpulseFeatures:
    """What one candidate impulse looked like (units in the names; NaN: not measurable).

    Attributes
    ----------
    peak_g : float
        Largest baseline residual of the filtered specific force, G.
    score : float
        Largest trigger score (residual over the per-axis trigger levels; > 1 opened it).
    duration_s : float
        Time the residual along the impulse direction stayed above half its peak, seconds.
    dv_imu_mps : float
        Impulse per unit mass along the impulse direction (integral of the specific force above
        the pre-impulse baseline), m/s.
    axial_fraction : float
        Share of the peak residual along the thrust axis (0 across it, 1 along it).
    approach_mps : float
        Speed towards the contact point before the impulse: ``-(v_before . n)``, m/s (mocap).
    rebound_mps : float
        Speed away from it after the impulse: ``v_after . n``, m/s (mocap).
    agreement : float
        Mocap velocity change along n over the IMU impulse (``(approach + rebound) / dv_imu``).
    turn_rate_radps : float
        Mean angular speed of the vehicle over the window before the onset, rad/s (attitude).
    """

    peak_g: float
    score: float
    duration_s: float
    dv_imu_mps: float
    axial_fraction: float
    approach_mps: float = math.nan
    rebound_mps: float = math.nan
    agreement: float = math.nan
    turn_rate_radps: float = math.nan

    @property
    def has_mocap(self) -> bool:
        return math.isfinite(self.approach_mps) and math.isfinite(self.rebound_mps)

    @property
    def rebound(self) -> bool:
        """The normal velocity reversed: approaching before, moving away after."""
        return self.has_mocap and self.approach_mps > 0.05 and self.rebound_mps > 0.02

    def as_dict(self) -> dict[str, float | None]:
        """The features by name, JSON-ready: None where not measurable (NaN: no mocap)."""
        return {
            k: float(v) if math.isfinite(v) else None for k, v in dataclasses.asdict(self).items()
        }


def model_inputs(f: ImpulseFeatures) -> dict[str, float]:
    """The named inputs of the logistic model, transformed to comparable ranges."""
    z = {
        "log_duration_ms": math.log(max(f.duration_s, 1e-3) * 1e3),
        "log_dv_imu": math.log(max(f.dv_imu_mps, 1e-3)),
        "log_peak_g": math.log(max(f.peak_g, 1e-3)),
        "axial_fraction": f.axial_fraction,
    }
    if math.isfinite(f.turn_rate_radps):
        # floored at a real airframe's steady wobble, capped where any manoeuvre is obvious
        z["log_turn_rate"] = math.log(
            float(np.clip(f.turn_rate_radps, TURN_RATE_FLOOR_RADPS, TURN_RATE_CAP_RADPS))
        )
    if f.has_mocap:
        z.update(
            approach=float(np.clip(f.approach_mps, -1.0, 2.0)),
            rebound=float(np.clip(f.rebound_mps, -1.0, 2.0)),
            reversal=float(np.clip(min(f.approach_mps, f.rebound_mps), -1.0, 1.0)),
            agreement=float(np.clip(f.agreement, -1.0, 3.0)) if math.isfinite(f.agreement) else 0.0,
            log_dv_per_approach=math.log(max(f.dv_imu_mps, 1e-3) / max(f.approach_mps, 0.05)),
        )
    return z


def design(x: np.ndarray, degree: int) -> np.ndarray:
    """Rows of standardised inputs -> the logistic model's terms: the inputs themselves, and
    with ``degree`` 2 also every product of two of them, squares included (``x_i x_j`` for
    ``i <= j`` in row-major order). One function for the fit and the prediction, so the
    order of the coefficients cannot drift between them."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    if degree == 1:
        return x
    i, j = np.triu_indices(x.shape[1])
    return np.hstack([x, x[:, i] * x[:, j]])


def n_terms(n_inputs: int, degree: int) -> int:
    """Number of terms :func:`design` makes of ``n_inputs`` inputs."""
    return n_inputs if degree == 1 else n_inputs + n_inputs * (n_inputs + 1) // 2


@dataclasses.dataclass(frozen=True)
class Logistic:
    """``p = sigmoid(intercept + coef . design(clip((z - mean) / scale), degree))`` on named
    inputs.

    With ``degree`` 2 the model also weighs products of two inputs: a touch is told from a gust
    by combinations (a short impulse *and* a rebound that follows from the approach), which
    one weight per input cannot express. ``clip_sd`` bounds each standardised input first, so
    a reading far outside the training flights (another airframe) cannot dominate by its square.
    The shipped model is of degree 1: the second degree extrapolates badly where the training
    flights are thin (``groundstation.bench.detector.EVIDENCE_FITS``).
    """

    names: tuple[str, ...]
    mean: tuple[float, ...]
    scale: tuple[float, ...]
    coef: tuple[float, ...]
    intercept: float
    degree: int = 1
    clip_sd: float | None = None

    def __post_init__(self) -> None:
        n = len(self.names)
        if not (len(self.mean) == len(self.scale) == n) or n == 0:
            raise ConfigError("evidence model: names, mean and scale must have one length")
        if self.degree not in (1, 2):
            raise ConfigError(f"evidence model: degree must be 1 or 2, not {self.degree}")
        if len(self.coef) != n_terms(n, self.degree):
            raise ConfigError(
                f"evidence model: {n} inputs of degree {self.degree} need "
                f"{n_terms(n, self.degree)} coefficients, not {len(self.coef)}"
            )
        if self.clip_sd is not None and not self.clip_sd > 0:
            raise ConfigError(f"evidence model: clip_sd must be positive, not {self.clip_sd}")

    def standardise(self, x: np.ndarray) -> np.ndarray:
        """Rows of raw inputs (in ``names`` order) -> standardised, clipped inputs."""
        s = (np.asarray(x, dtype=float) - np.asarray(self.mean)) / np.asarray(self.scale)
        return s if self.clip_sd is None else np.clip(s, -self.clip_sd, self.clip_sd)

    def probability(self, z: dict[str, float]) -> float:
        """An input missing from ``z`` (a feature not measurable) counts as its training mean:
        it neither raises nor lowers ``p`` (its standardised value and all its products are 0)."""
        x = np.array([z.get(k, m) for k, m in zip(self.names, self.mean, strict=True)])
        terms = design(self.standardise(x), self.degree)[0]
        s = self.intercept + float(np.dot(self.coef, terms))
        return float(1.0 / (1.0 + math.exp(-max(min(s, 50.0), -50.0))))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Logistic:
        """A block of ``evidence_model.json``; ``degree`` (1) and ``clip_sd`` (none) are
        optional, so models written before they existed load unchanged."""
        try:
            clip = d.get("clip_sd")
            return cls(
                tuple(d["names"]),
                tuple(float(v) for v in d["mean"]),
                tuple(float(v) for v in d["scale"]),
                tuple(float(v) for v in d["coef"]),
                float(d["intercept"]),
                int(d.get("degree", 1)),
                None if clip is None else float(clip),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"evidence model: bad logistic block ({exc})") from None


@dataclasses.dataclass(frozen=True)
class EvidenceModel:
    """Two logistic models: with mocap features, and from the IMU alone."""

    with_mocap: Logistic
    imu_only: Logistic
    provenance: str = ""

    def p_false(self, f: ImpulseFeatures) -> float:
        """Probability that the impulse was not a contact with a structure."""
        z = model_inputs(f)
        if f.has_mocap and all(k in z for k in self.with_mocap.names):
            return self.with_mocap.probability(z)
        return self.imu_only.probability(z)

    def to_dict(self) -> dict:
        return {
            "schema": "groundstation-evidence/1",
            "provenance": self.provenance,
            "with_mocap": self.with_mocap.to_dict(),
            "imu_only": self.imu_only.to_dict(),
        }

    @classmethod
    def load(cls, path: str | Path | None = None) -> EvidenceModel:
        """The model in ``path`` (default: the bundled one).

        Raises
        ------
        ConfigError
            Missing or malformed file (the message names it).
        """
        p = Path(path) if path else BUNDLED_MODEL
        try:
            d = json.loads(p.read_text())
        except FileNotFoundError:
            raise ConfigError(
                f"evidence model {str(p)!r} does not exist",
                hint="leave contact.evidence_model empty for the bundled model",
            ) from None
        except (OSError, json.JSONDecodeError) as exc:
            raise ConfigError(f"evidence model {str(p)!r} is not readable JSON: {exc}") from None
        if not isinstance(d, dict) or d.get("schema") != "groundstation-evidence/1":
            raise ConfigError(f"evidence model {str(p)!r} is not a groundstation-evidence/1 file")
        return cls(
            Logistic.from_dict(d.get("with_mocap", {})),
            Logistic.from_dict(d.get("imu_only", {})),
            str(d.get("provenance", "")),
        )
