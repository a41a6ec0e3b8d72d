"""Drivers (prescribed motions): each one an exact rheonomic ``CoordinateConstraint`` on a
coordinate of the driven body's node, its offset given by ``offsetUserFunction``, its force
output the driver's effort.

The constraint acts on the node coordinate without its reference value, so the offset is
``value(t) - reference``. The node is at the centre of mass with the body's frame, so an
``angle`` driver is the node's rotation coordinate (2-D) and a ``coordinate`` driver is a
node position coordinate: only at a point at the centre of mass (a particle's point); at
any other point the world coordinate is nonlinear in the node's coordinates and is not
modelled. Sign (measured on tests/data/driven_rod.toml against its closed form): the
constraint's Force output is the opposite of the generalized force it applies to the node
coordinate, so the driver's effort on the body (N m about z, or N along the axis) is its
negative.
"""

from __future__ import annotations

import numpy as np

from ...case.mechanism import Case, Driver
from ...errors import Unsupported
from .bodies import centre_state
from .system import Build

AXES = {"x": 0, "y": 1, "z": 2}
EFFORT_SIGN = -1.0  # see the module docstring (measured)


def check(case: Case) -> None:
    """Raise Unsupported for a driver the adapter cannot prescribe exactly."""
    for d in case.drivers:
        kind = getattr(d, "type", None)
        if kind not in ("angle", "coordinate"):
            raise Unsupported(f"driver {d.name}: type {kind!r} is not modelled")
        b = case.body(d.body)
        if d.type == "angle" and (case.dimension != 2 or b.kind == "particle"):
            raise Unsupported(f"driver {d.name}: an angle driver needs a rigid 2-D body")
        if d.type == "coordinate" and np.linalg.norm(b.points[d.point] - b.com) > 1e-12:
            raise Unsupported(f"driver {d.name}: point {d.point} of {d.body} is not its centre "
                              "of mass; the Exudyn adapter prescribes node coordinates "
                              "(CoordinateConstraint) only, and a point off the node moves "
                              "nonlinearly with them")


def _coordinate(build: Build, d: Driver) -> tuple[int, float]:
    """(node coordinate index, its reference value at t = 0) of the driven quantity."""
    if d.type == "angle":
        return 2, float(build.init[d.body].angle)
    i = AXES[d.axis]
    pos, _ = centre_state(build, build.case.body(d.body))
    return i, float(pos[i])


def add(build: Build, d: Driver):
    """The driver's constraint; returns reader(get) -> (T,) effort on the body."""
    i, ref = _coordinate(build, d)

    def offset(mbs, t, item, l_offset):
        return d.v0 + d.rate * t + 0.5 * d.accel * t * t - ref

    co = build.mbs.AddObject(build.ei.CoordinateConstraint(
        markerNumbers=[build.node_coordinate(None, 0), build.node_coordinate(d.body, i)],
        offsetUserFunction=offset))
    sf = build.object_sensor(co, build.exu.OutputVariableType.Force)
    build.note_once("drivers: CoordinateConstraint on the node coordinate with an "
                    "offsetUserFunction (exact rheonomic constraint); effort = -Force output")
    return lambda get: EFFORT_SIGN * get(sf)[:, 0]
