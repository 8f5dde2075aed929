"""Per-rig configuration: time-of-flight calibration, limits and timeouts, validated.

A rig config is a small TOML or JSON file. Every key is optional (defaults below suit the
emulator); unknown keys and out-of-range values are rejected with a message naming the key.

Example ``rig.toml``::

    port_baudrate = 115200
    telemetry_timeout_s = 1.0
    hard_pressure_limit_pa = 12000.0

    [tof_left]            # height_mm = scale * tof + offset_mm
    scale = -1.0
    offset_mm = 120.0

    [tof_right]
    scale = -1.0
    offset_mm = 120.0

Heights are millimetres of the plate above the membrane plane, pressures pascals (gauge).
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

TOF_DROPOUT = 400.0  # a time-of-flight reading >= this is a sensor dropout


class ConfigError(ValueError):
    """An invalid rig configuration; the message names the file and key."""


@dataclass(frozen=True)
class Affine:
    """``height_mm = scale * tof + offset_mm`` for one time-of-flight sensor."""

    scale: float = -1.0
    offset_mm: float = 120.0

    def height_mm(self, tof: float) -> float:
        return self.scale * tof + self.offset_mm

    def tof(self, height_mm: float) -> float:
        """Inverse map (used by the emulator to synthesise readings)."""
        return (height_mm - self.offset_mm) / self.scale


@dataclass(frozen=True)
class RigConfig:
    """Calibration, limits and timeouts of one rig (mm, Pa, s)."""

    tof_left: Affine = field(default_factory=Affine)
    tof_right: Affine = field(default_factory=Affine)
    port_baudrate: int = 115200
    telemetry_timeout_s: float = 1.0  # silence longer than this (wall clock) is a fault
    heartbeat_interval_s: float = 0.2  # wall clock; a fifth of the controller's 1 s watchdog
    safe_state_deadline_s: float = 0.1  # budget to reach the safe state after a fault
    hard_pressure_limit_pa: float = 12000.0  # above this: safe state at once
    height_min_mm: float = 0.0
    height_max_mm: float = 75.0
    height_tolerance_mm: float = 1.0
    set_height_timeout_s: float = 60.0  # rig seconds for one set-height
    max_tilt_mm: float = 5.0  # left/right disagreement beyond this is reported
    trial_timeout_s: float = 120.0  # rig seconds for one inflation or deflation
    pressurise_timeout_s: float = 15.0  # pumping this long without reaching burst_min_peak_pa: fault
    zero_pressure_pa: float = 100.0  # deflation ends below this
    burst_drop_fraction: float = 0.4  # pressure falling this far below its peak while
    burst_min_peak_pa: float = 500.0  # pumping (peak above burst_min_peak_pa) is a burst
    sensor_dropout_timeout_s: float = 5.0  # both heights unknown this long (rig s) -> fault
    push_lowers_plate: bool = True  # actuator "push" moves the plate towards the membrane
    time_unit_s: float = 1.0  # telemetry time field times this = seconds
    fsync_interval_s: float = 0.0  # 0: fsync the journal right after every write

    def __post_init__(self) -> None:
        def positive(name: str) -> None:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{name} must be a positive number, got {v!r}")

        for name in (
            "telemetry_timeout_s",
            "heartbeat_interval_s",
            "safe_state_deadline_s",
            "hard_pressure_limit_pa",
            "height_tolerance_mm",
            "set_height_timeout_s",
            "max_tilt_mm",
            "trial_timeout_s",
            "pressurise_timeout_s",
            "zero_pressure_pa",
            "burst_min_peak_pa",
            "sensor_dropout_timeout_s",
            "time_unit_s",
        ):
            positive(name)
        if not (0.0 <= self.fsync_interval_s <= 10.0):
            raise ConfigError(f"fsync_interval_s must be in [0, 10] s, got {self.fsync_interval_s}")
        if not (0.05 <= self.burst_drop_fraction <= 0.95):
            raise ConfigError(f"burst_drop_fraction must be in [0.05, 0.95], got {self.burst_drop_fraction}")
        if self.port_baudrate not in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600):
            raise ConfigError(f"port_baudrate {self.port_baudrate} is not a standard rate")
        if not (self.height_min_mm < self.height_max_mm):
            raise ConfigError(
                f"height_min_mm ({self.height_min_mm}) must be below height_max_mm ({self.height_max_mm})"
            )
        for side in ("tof_left", "tof_right"):
            a = getattr(self, side)
            if not (math.isfinite(a.scale) and math.isfinite(a.offset_mm) and a.scale != 0):
                raise ConfigError(f"{side}: scale must be finite and non-zero, offset finite, got {a}")

    def height_mm(self, left_tof: float, right_tof: float) -> tuple[float, float]:
        """Left and right heights (mm); NaN for a dropped-out sensor."""
        lh = self.tof_left.height_mm(left_tof) if left_tof < TOF_DROPOUT else math.nan
        rh = self.tof_right.height_mm(right_tof) if right_tof < TOF_DROPOUT else math.nan
        return lh, rh

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "config") -> "RigConfig":
        """Build from a plain dict (as read from TOML/JSON), checking names and types."""
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: the top level must be a table/object")
        known = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(known))
        if unknown:
            raise ConfigError(f"{source}: unknown key(s) {unknown}; known: {sorted(known)}")
        kwargs: dict[str, Any] = {}
        for name, value in data.items():
            if name in ("tof_left", "tof_right"):
                if not isinstance(value, dict) or set(value) - {"scale", "offset_mm"}:
                    raise ConfigError(f"{source}: {name} must be a table with keys scale and offset_mm, got {value!r}")
                try:
                    kwargs[name] = Affine(**{k: _number(source, f"{name}.{k}", v) for k, v in value.items()})
                except ConfigError:
                    raise
            elif name == "push_lowers_plate":
                if not isinstance(value, bool):
                    raise ConfigError(f"{source}: {name} must be true or false, got {value!r}")
                kwargs[name] = value
            elif name == "port_baudrate":
                if not isinstance(value, int) or isinstance(value, bool):
                    raise ConfigError(f"{source}: {name} must be an integer, got {value!r}")
                kwargs[name] = value
            else:
                kwargs[name] = _number(source, name, value)
        try:
            return cls(**kwargs)
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}") from None

    @classmethod
    def load(cls, path: str | Path) -> "RigConfig":
        """Read a ``.toml`` or ``.json`` rig config."""
        path = Path(path)
        try:
            raw = path.read_bytes()
        except OSError as exc:
            raise ConfigError(f"cannot read rig config {path}: {exc.strerror}") from None
        try:
            if path.suffix.lower() == ".json":
                data = json.loads(raw.decode("utf-8"))
            elif path.suffix.lower() == ".toml":
                data = tomllib.loads(raw.decode("utf-8"))
            else:
                raise ConfigError(f"rig config {path} must end in .toml or .json")
        except (UnicodeDecodeError, json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"rig config {path} is not valid {path.suffix[1:].upper()}: {exc}") from None
        return cls.from_dict(data, source=str(path))


def _number(source: str, name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{source}: {name} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ConfigError(f"{source}: {name} must be finite, got {value}")
    return value
