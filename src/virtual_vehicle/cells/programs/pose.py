"""Program ``"pose"``: parcels driven to target poses (or along waypoints) from the sensors, by the cells under each
parcel (:class:`~virtual_vehicle.cells.tracking.DistributedPose`) or by one central computer
(:class:`~virtual_vehicle.cells.control.PoseControl`); its task report. Units: m, rad, s, m/s."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from virtual_vehicle.cells.programs.base import (BuildContext, ControlSetup, FieldError, Markers, Pose,
                                                 ProgramOptions, setup_for)


class Retarget(BaseModel):
    """A new target pose for one parcel from time ``t`` (s) on: ``parcel`` (its name) is driven to ``target`` =
    [x, y, theta] (m, m, rad) from the first control tick at or after ``t`` (as the live viewer records one)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)
    t: Annotated[float, Field(ge=0, le=1e7)]
    parcel: str
    target: Pose


class PoseOptions(ProgramOptions):
    """``program = "pose"`` is a closed loop from the sensors: it drives parcel k to ``targets[k]`` = [x, y, theta]
    (m, m, rad) with twist ``gain`` (1/s) times the estimated error, wheels limited to ``speed`` (m/s), stopping
    within ``tolerance`` = [m, rad]; with ``waypoints`` (one list of [x, y, theta] per parcel) it transports each
    along that path, passing a waypoint within ``pass_radius`` (m). The cells under each parcel estimate its pose
    together and drive it (:mod:`~virtual_vehicle.cells.tracking`), or with ``central`` = true one computer reads
    every sensor and commands every cell (:class:`~virtual_vehicle.cells.control.PoseControl`). ``retargets`` (a
    ``[[control.retargets]]`` table each: ``t``, ``parcel``, ``target``) change a parcel's target during the run; the
    report measures each parcel against its last target."""

    program: Literal["pose"]
    speed: Annotated[float, Field(gt=0, le=1e3)] = 0.2
    targets: list[Pose]
    waypoints: list[list[Pose]] | None = None
    pass_radius: Annotated[float, Field(gt=0, le=10)] = 0.01
    gain: Annotated[float, Field(gt=0, le=1e3)] = 2.0
    tolerance: tuple[Annotated[float, Field(gt=0, le=1)], Annotated[float, Field(gt=0, le=3.2)]] = (5e-4, 0.0035)
    central: bool = False
    retargets: list[Retarget] = []

    @model_validator(mode="after")
    def _one_path_per_target(self):
        if self.waypoints is not None and len(self.waypoints) != len(self.targets):
            raise ValueError("waypoints: one list per parcel, like targets")
        return self

    def top_speed(self) -> float:
        """The wheels' speed limit (m/s)."""
        return self.speed



Options = PoseOptions
"""The ``[control]`` table of this program."""

def build(options: PoseOptions, ctx: BuildContext) -> ControlSetup:
    """The distributed pose loop (each cell told its position, drive directions and sensor points when installed),
    or with ``central`` the central controller."""
    from virtual_vehicle.cells.control import PoseControl

    c = options
    if len(c.targets) != len(ctx.specs):
        raise FieldError("control.targets", f"needs one target per parcel: {len(ctx.specs)}, got {len(c.targets)}")
    retargets = resolve_retargets(c, [s.name for s in ctx.specs])
    if c.central:
        program = PoseControl(ctx.cells, ctx.sensors.points, ctx.specs, ctx.states, c.targets, gain=c.gain,
                              max_speed=c.speed, tolerance=c.tolerance, period=c.period, waypoints=c.waypoints,
                              pass_radius=c.pass_radius, retargets=retargets)
        return setup_for(c, ctx, program)
    from virtual_vehicle.cells.estimate import sensor_spacing
    from virtual_vehicle.cells.tracking import DistributedPose

    program = DistributedPose(ctx.specs, ctx.states, c.targets, spacing=sensor_spacing(ctx.sensors.points),
                              gain=c.gain, max_speed=c.speed, tolerance=c.tolerance, period=c.period,
                              waypoints=c.waypoints, pass_radius=c.pass_radius, max_age=c.max_age,
                              retargets=retargets)
    config = {"position": ctx.cells.positions, "directions": ctx.cells.active_directions,
              "sensor_points": ctx.sensors.points}  # what each cell is told when it is installed
    return setup_for(c, ctx, program, config)


def resolve_retargets(options: PoseOptions, names: list[str]) -> list[tuple[float, int, tuple]]:
    """``options.retargets`` as (t s, parcel index, target pose) in time order, the parcels found by ``names``.
    Raises FieldError for a parcel no parcel is named."""
    out = []
    for k, r in enumerate(options.retargets):
        if r.parcel not in names:
            raise FieldError(f"control.retargets[{k}].parcel", f"no parcel is named {r.parcel!r}")
        out.append((r.t, names.index(r.parcel), r.target))
    return sorted(out, key=lambda r: r[0])


def final_targets(options: PoseOptions, names: list[str]) -> list[tuple]:
    """Each parcel's last target pose (x, y, theta; m, m, rad): its ``targets`` row as changed by ``retargets``."""
    targets = [tuple(t) for t in options.targets]
    for _, j, pose in resolve_retargets(options, names):
        targets[j] = tuple(pose)
    return targets


def report(result) -> dict:
    """Outcome of every parcel of a pose run (program ``"pose"``: to a target pose, along waypoints, or turned in
    place) and the run's totals.

    Per parcel: the final error (mm, degrees; the heading wrapped to the outline's rotational symmetry), the time it
    settled within 5 mm and 2 degrees of its target for good (None if it never did), and with waypoints the largest
    distance (mm) of its centre of mass from the path start -> waypoints -> target. Totals: how many settled, the mean
    and largest final errors and settling times, ``throughput_per_hour`` (settled parcels per hour of the run), and
    ``collisions`` (pairs of parcels that started pushing each other: must be 0).
    """
    from virtual_vehicle.cells.control import path_deviation, pose_error, settled_at

    sc = result.setup.scenario
    ways = sc.control.waypoints or [[] for _ in result.parcels]
    rows = []
    targets = final_targets(sc.control, [pr.spec.name for pr in result.parcels])
    for pr, target, way in zip(result.parcels, targets, ways):
        tr = pr.trajectory
        dist, ang = pose_error(pr.spec, tr.states[-1], target)
        row = {"name": pr.spec.name, "target": dict(zip(("x", "y", "theta"), target)), "final_error_mm": dist * 1e3,
               "final_error_deg": float(np.degrees(ang)),
               "settled_within_5mm_2deg_at_s": settled_at(pr.spec, tr.times, tr.states, target)}
        if way:
            row["max_path_deviation_mm"] = path_deviation(tr.states, [tr.states[0, :3], *way, target]) * 1e3
        rows.append(row)
    settled = [r["settled_within_5mm_2deg_at_s"] for r in rows if r["settled_within_5mm_2deg_at_s"] is not None]
    paths = [r["max_path_deviation_mm"] for r in rows if "max_path_deviation_mm" in r]
    return {
        "parcels": rows,
        "settled": len(settled),
        "collisions": int(result.stats.get("plant", {}).get("parcel_contacts", 0)),
        "throughput_per_hour": len(settled) / sc.duration * 3600.0,
        "final_error_mean_mm": float(np.mean([r["final_error_mm"] for r in rows])),
        "final_error_max_mm": float(np.max([r["final_error_mm"] for r in rows])),
        "final_error_mean_deg": float(np.mean([r["final_error_deg"] for r in rows])),
        "final_error_max_deg": float(np.max([r["final_error_deg"] for r in rows])),
        "settle_time_mean_s": float(np.mean(settled)) if settled else None,
        "settle_time_max_s": float(np.max(settled)) if settled else None,
        "max_path_deviation_mm": float(np.max(paths)) if paths else None,
    }


SUMMARY = "pose"
"""The run summary's block holding :func:`report` (per-parcel rows merged into the summary's parcels)."""
COMPARED = (("settled", "settled within 5 mm and 2 deg"), ("collisions", "collisions"),
            ("throughput_per_hour", "parcels settled per hour"), ("final_error_mean_mm", "mean final error (mm)"),
            ("final_error_max_mm", "largest final error (mm)"), ("final_error_mean_deg", "mean final error (deg)"),
            ("final_error_max_deg", "largest final error (deg)"), ("settle_time_mean_s", "mean time to settle (s)"),
            ("settle_time_max_s", "longest time to settle (s)"),
            ("max_path_deviation_mm", "largest deviation from the path (mm)"))
"""(report key, label) of what ``virtual-vehicle compare`` puts side by side."""
CENTRAL = True
"""``central = true`` runs the same task on one central computer."""
LABELS = False
"""The cells read no labels on the parcels."""


def markers(setup) -> Markers:
    """Each parcel's (last) target pose."""
    return Markers(targets=final_targets(setup.scenario.control, [s.name for s in setup.specs]))
