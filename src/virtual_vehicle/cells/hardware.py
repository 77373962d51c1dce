"""Cell hardware: binary presence sensors (paper Sections 1 and 2.2).

Units: m. Each cell carries up to five phototransistors that see the shadow of a parcel above them. A sensor reads 1
when a parcel's footprint covers its point. Offsets are given in the cell's own frame (x along its wheel 0, y along
wheel 1); the default is the centre and the four edge midpoints, half a pitch out.

Imperfections: each reading is independently flipped from 0 to 1 with probability ``false_positive`` and from 1 to
0 with ``false_negative`` (one numpy Generator, seeded); faulty sensors are stuck on or stuck off.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from virtual_vehicle.model.layout import CellArray
from virtual_vehicle.model import state_data
from virtual_vehicle.model.parcel import ParcelSpec, PointGrid, covered_pairs

MAX_SENSORS = 5


def default_offsets(pitch: float) -> np.ndarray:
    """Centre, then the east, north, west and south edge midpoints (cell frame), m."""
    h = pitch / 2
    return np.array([[0.0, 0.0], [h, 0.0], [0.0, h], [-h, 0.0], [0.0, -h]])


@dataclass(frozen=True, eq=False)
class Sensors:
    """The presence sensors of an array.

    Attributes:
        cells: the array.
        offsets: (S, 2) sensor offsets in each cell's frame, m (S <= 5).
        false_positive, false_negative: per-reading flip probabilities.
        stuck_on, stuck_off: (n, S) bool fault masks (stuck on wins if both).
        seed: seed of the noise; each run draws from its own ``numpy.random.default_rng(seed)``.
    """

    cells: CellArray
    offsets: np.ndarray
    false_positive: float = 0.0
    false_negative: float = 0.0
    stuck_on: np.ndarray | None = None
    stuck_off: np.ndarray | None = None
    seed: int = 0

    def __post_init__(self):
        off = np.asarray(self.offsets, dtype=float)
        if off.ndim != 2 or off.shape[1] != 2 or not 1 <= len(off) <= MAX_SENSORS or not np.all(np.isfinite(off)):
            raise ValueError(f"offsets must be 1 to {MAX_SENSORS} finite [x, y] offsets in m")
        for name in ("false_positive", "false_negative"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {v}")
        object.__setattr__(self, "offsets", off)
        shape = (self.cells.n, len(off))
        for name in ("stuck_on", "stuck_off"):
            mask = getattr(self, name)
            mask = np.zeros(shape, bool) if mask is None else np.asarray(mask, dtype=bool)
            if mask.shape != shape:
                raise ValueError(f"{name}: the fault mask must have shape {shape}")
            object.__setattr__(self, name, mask)

    @property
    def count(self) -> int:
        """Sensors per cell."""
        return len(self.offsets)

    @cached_property
    def points(self) -> np.ndarray:
        """(n, S, 2) world positions of every sensor, m."""
        u = self.cells.drive_directions  # (n, 2, 2): wheel 0 and wheel 1 directions
        return self.cells.positions[:, None, :] + self.offsets[None, :, 0, None] * u[:, None, 0, :] \
            + self.offsets[None, :, 1, None] * u[:, None, 1, :]

    @cached_property
    def _grid(self) -> PointGrid:
        return PointGrid(self.points)

    def covered(self, specs: list[ParcelSpec], states, active=None) -> np.ndarray:
        """(n, S) True where a (active) parcel's footprint covers the sensor point: the noiseless truth."""
        n, S = self.cells.n, self.count
        out = np.zeros(n * S, dtype=bool)
        on = [k for k in range(len(specs)) if active is None or active[k]]
        point = covered_pairs([specs[k] for k in on], [states[k] for k in on], self._grid)[1]
        out[point] = True
        return out.reshape(n, S)

    def read(self, specs: list[ParcelSpec], states, rng: np.random.Generator, active=None,
             rows: np.ndarray | None = None) -> np.ndarray:
        """(n, S) readings: the truth, flipped at the false-positive/negative rates (drawn from ``rng``, one number a
        sensor, only when a rate is not zero), then the stuck faults. ``rows``: only these cells read (indices; the
        others' rows are False and draw no noise), as cells on their own clocks do at their ticks."""
        reading = self.covered(specs, states, active)
        if rows is not None:
            rows = np.asarray(rows, dtype=np.int64)
            full, reading = reading, reading[rows]
        if self.false_positive or self.false_negative:
            r = rng.random(reading.shape)
            reading = np.where(reading, r >= self.false_negative, r < self.false_positive)
        if self._stuck is not None:
            on, off = self._stuck
            reading = (reading | on[rows]) & ~off[rows] if rows is not None else (reading | on) & ~off
        if rows is not None:
            full[:] = False
            full[rows] = reading
            reading = full
        return reading

    @cached_property
    def _stuck(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The readings forced on and off by stuck sensors (stuck on wins), None when no sensor is stuck."""
        if not (self.stuck_on.any() or self.stuck_off.any()):
            return None
        return self.stuck_on, self.stuck_off & ~self.stuck_on


@dataclass(frozen=True)
class MotorParams:
    """A roller wheel driven by a DC motor through a gearbox, PWM H-bridge and quadrature encoder, with a PI speed
    loop in its cell (paper 2.1-2.2). Defaults: a small 12 V gearmotor; units SI.

    supply_voltage (V): the H-bridge's limit, |V| <= supply. resistance (ohm), torque_constant (N m/A, also the
    back-EMF constant in V s/rad), rotor_inertia (kg m^2) and viscous_damping (N m s/rad) on the motor side;
    gear_ratio (motor turns per wheel turn); wheel_radius (m) and wheel_inertia (kg m^2) on the wheel side;
    encoder_counts per motor revolution; kp (V per m/s) and ki (V per m) of the PI loop on surface speed.
    Inductance is neglected (electrical time constant << mechanical).
    """

    supply_voltage: float = 12.0
    resistance: float = 2.0
    torque_constant: float = 0.02
    rotor_inertia: float = 2e-6
    viscous_damping: float = 1e-6
    gear_ratio: float = 30.0
    wheel_radius: float = 0.02
    wheel_inertia: float = 2e-5
    encoder_counts: int = 512
    kp: float = 20.0
    ki: float = 1500.0

    def __post_init__(self):
        for name in ("supply_voltage", "resistance", "torque_constant", "rotor_inertia", "gear_ratio",
                     "wheel_radius", "wheel_inertia"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.viscous_damping < 0 or self.kp < 0 or self.ki < 0 or self.encoder_counts < 1:
            raise ValueError("viscous_damping, kp and ki must be >= 0 and encoder_counts >= 1")

    @property
    def inertia(self) -> float:
        """Inertia reflected to the wheel shaft, kg m^2."""
        return self.wheel_inertia + self.gear_ratio**2 * self.rotor_inertia

    @property
    def damping(self) -> float:
        """Wheel-side damping including back-EMF, N m s/rad: G^2 k^2 / R + G^2 b."""
        g, k = self.gear_ratio, self.torque_constant
        return g * g * (k * k / self.resistance + self.viscous_damping)

    @property
    def time_constant(self) -> float:
        """Mechanical time constant of the unloaded drive, s."""
        return self.inertia / self.damping

    def steady_speed(self, voltage, load_force):
        """Wheel surface speed (m/s) the drive settles at under ``voltage`` (V) and a friction ``load_force`` (N)
        that the parcel exerts back on the wheel surface along its drive direction."""
        gain = self.gear_ratio * self.torque_constant / self.resistance  # N m per V at the wheel
        return self.wheel_radius * (gain * voltage - self.wheel_radius * load_force) / self.damping


PROFILES: dict[str, dict] = {
    "industrial": dict(supply_voltage=24.0, resistance=2.0, torque_constant=0.05, rotor_inertia=1e-4,
                       viscous_damping=1e-5, gear_ratio=6.0, wheel_radius=0.025, wheel_inertia=0.032,
                       encoder_counts=1024, kp=60.0, ki=200.0),
}
"""Named :class:`MotorParams` settings (SI units) a scenario's ``[wheels] profile`` selects.

``"industrial"``: the drive of a commercial modular conveyor cell as its test specification states it (wheels to
1.1 m/s, 2.5 m/s^2, 100 Hz control, about 150 ms wheel response), met by this motor model: a 24 V gearmotor (6:1,
25 mm rollers) runs unloaded to 1.98 m/s, so 1.1 m/s is reached with headroom; the reflected inertia (roller module
and gearbox, 0.036 kg m^2 at the wheel) against the stall torque at full voltage caps the acceleration at 2.5 m/s^2
(the model has no separate ramp: the limit is the drive's torque); the PI loop (60 V per m/s, 200 V per m) answers
a small step in 140 ms (63 %), 9 % overshoot, and a step to 1.1 m/s in 0.63 s (90 %), under a 2 N friction load,
at a 10 ms control period (``[wheels] period`` / ``[control] period``)."""


class WheelDrives:
    """The drives of every wheel of an array (n cells x 2 wheels), stepped once per control period.

    ``step(command, load, period)`` takes the commanded surface speeds (n, 2) m/s and the load forces (n, 2) N
    (what the parcel's friction pushes back on each wheel surface, along its drive direction), runs each cell's PI
    loop on its encoder measurement, applies the saturated PWM voltage for the period, integrates the wheel exactly
    (first-order linear dynamics under constant voltage and load), and returns the mean surface speed over the
    period (n, 2) m/s, which the plant holds for that period.
    """

    def __init__(self, n: int, params: MotorParams = MotorParams()):
        self.p = params
        self.speed = np.zeros((n, 2))  # wheel surface speed, m/s
        self.angle = np.zeros((n, 2))  # motor shaft angle, rad
        self.counts = np.zeros((n, 2), dtype=np.int64)
        self.integral = np.zeros((n, 2))
        self.measured = np.zeros((n, 2))  # encoder estimate of surface speed, m/s
        self.voltage = np.zeros((n, 2))

    _ARRAYS = ("speed", "angle", "counts", "integral", "measured", "voltage")

    def to_data(self) -> dict:
        """The drives' state as data: (n, 2) arrays ``speed`` (m/s), ``angle`` (rad), encoder ``counts``, the PI
        loop's ``integral`` (m), ``measured`` (m/s) and ``voltage`` (V). The parameters are the setup's."""
        return {k: getattr(self, k) for k in self._ARRAYS}

    @classmethod
    def from_data(cls, d, params: MotorParams = MotorParams(), where: str = "drives") -> "WheelDrives":
        """The drives :meth:`to_data` wrote, with ``params``; raises ValueError for data of other keys, dtypes or
        shapes."""
        d = state_data.fields(d, cls._ARRAYS, where)
        n = len(state_data.array(d, "speed", "f", (None, 2), where))
        drives = cls(n, params)
        for k in cls._ARRAYS:
            setattr(drives, k, state_data.array(d, k, "i" if k == "counts" else "f", (n, 2), where))
        return drives

    def step(self, command: np.ndarray, load: np.ndarray, period: float) -> np.ndarray:
        """Apply speed ``command`` (n, 2, m/s) for ``period`` s against the friction ``load`` (n, 2, N) through the PI
        loop and motor model; returns the wheels' mean surface speed over the period (m/s) and updates the encoder
        reading."""
        p = self.p
        error = command - self.measured
        unsat = p.kp * error + p.ki * (self.integral + error * period)
        voltage = np.clip(unsat, -p.supply_voltage, p.supply_voltage)
        # anti-windup: integrate only where the output is not saturated against the error
        grow = (voltage == unsat) | (np.sign(error) != np.sign(unsat))
        self.integral = np.where(grow, self.integral + error * period, self.integral)
        target = p.steady_speed(voltage, load)
        tau = p.time_constant
        decay = np.exp(-period / tau)
        v0 = self.speed
        self.speed = target + (v0 - target) * decay
        mean = target + (v0 - target) * tau * (1 - decay) / period
        # encoder on the motor shaft: counts of whole increments of the angle
        self.angle = self.angle + mean * period / p.wheel_radius * p.gear_ratio
        counts = np.floor(self.angle * p.encoder_counts / (2 * np.pi)).astype(np.int64)
        self.measured = (counts - self.counts) * (2 * np.pi / p.encoder_counts) / p.gear_ratio * p.wheel_radius / period
        self.counts = counts
        self.voltage = voltage
        return mean
