"""The Exudyn system being built for one case: its items, markers and sensors.

Every factory of the adapter (bodies, joints, connectors, drivers) adds items through one
:class:`Build`, so how a body point becomes a marker is decided here only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...case.mechanism import GROUND, Case


def v3(v) -> list[float]:
    """A 2-D or 3-D vector as Exudyn's 3-vector (z = 0 in 2-D)."""
    out = [0.0, 0.0, 0.0]
    for i, x in enumerate(np.asarray(v, float).reshape(-1)):
        out[i] = float(x)
    return out


@dataclass
class Build:
    """One case's Exudyn system under construction.

    ``objs``/``nodes``: body name -> Exudyn object / node number (node at the centre of
    mass, node frame = body frame); ``notes``: what the model substituted, for the report.
    """

    exu: object
    ei: object
    case: Case
    init: object
    settings: dict
    mbs: object = None
    ground: int = -1
    objs: dict = field(default_factory=dict)
    nodes: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    _ground_coordinate: int | None = None

    def __post_init__(self):
        self._container = self.exu.SystemContainer()  # owns mbs: keep it alive
        self.mbs = self._container.AddSystem()
        self.ground = self.mbs.AddObject(self.ei.ObjectGround())

    def local(self, body: str, point: str) -> list[float]:
        """A body point relative to the body's centre of mass (the node), body axes, m."""
        if body == GROUND:
            return v3(self.case.ground[point])
        b = self.case.body(body)
        return v3(b.points[point] - b.com)

    def marker(self, body: str, point: str, rotation=None, rigid: bool = False,
               at=None) -> int:
        """A marker at a body point: position only, or rigid (``rigid`` or a joint frame
        ``rotation`` (3, 3) in the body frame, given as the marker's localHT). ``at``: the
        marker sits instead where this world point (d,) is at t = 0."""
        ei, num = self.ei, self.ground if body == GROUND else self.objs[body]
        local = self.local(body, point) if at is None else self.local_of(body, at)
        if rotation is not None:
            ht = self.exu.HT(rotation=np.asarray(rotation, float), translation=local)
            return self.mbs.AddMarker(ei.MarkerBodyRigid(bodyNumber=num, localHT=ht))
        kind = ei.MarkerBodyRigid if rigid else ei.MarkerBodyPosition
        return self.mbs.AddMarker(kind(bodyNumber=num, localPosition=local))

    def world0(self, body: str, point: str) -> np.ndarray:
        """World position (d,) of a body point at t = 0, m."""
        if body == GROUND:
            return np.asarray(self.case.ground[point], float)
        st = self.init[body]
        return np.asarray(st.origin, float) + np.asarray(st.rotation, float) @ \
            self.case.body(body).points[point]

    def local_of(self, body: str, world) -> list[float]:
        """The body-fixed point at world position ``world`` (d,) at t = 0, relative to the
        centre of mass, body axes, m."""
        if body == GROUND:
            return v3(world)
        st = self.init[body]
        p = np.asarray(st.rotation, float).T @ (np.asarray(world, float) - st.origin)
        return v3(p - self.case.body(body).com)

    def node_coordinate(self, body: str | None, i: int) -> int:
        """A marker on coordinate ``i`` of a body's node (``None``: a fixed zero coordinate,
        made once)."""
        ei = self.ei
        if body is not None:
            return self.mbs.AddMarker(ei.MarkerNodeCoordinate(nodeNumber=self.nodes[body],
                                                              coordinate=i))
        if self._ground_coordinate is None:
            gn = self.mbs.AddNode(ei.NodePointGround(referenceCoordinates=[0.0, 0.0, 0.0]))
            self._ground_coordinate = self.mbs.AddMarker(
                ei.MarkerNodeCoordinate(nodeNumber=gn, coordinate=0))
        return self._ground_coordinate

    def sensor(self, kind, **kw) -> int:
        """A sensor stored in memory (at the output interval), never written to a file."""
        return self.mbs.AddSensor(kind(storeInternal=True, writeToFile=False, **kw))

    def object_sensor(self, obj: int, output) -> int:
        return self.sensor(self.ei.SensorObject, objectNumber=obj, outputVariableType=output)

    def node_sensor(self, body: str, output) -> int:
        return self.sensor(self.ei.SensorNode, nodeNumber=self.nodes[body],
                           outputVariableType=output)

    def rotation0(self, body: str) -> np.ndarray:
        """(3, 3) body-to-world rotation at t = 0 (a 2-D frame turns about z)."""
        return np.eye(3) if body == GROUND else self.init[body].rotation3()

    def note_once(self, text: str) -> None:
        if text not in self.notes:
            self.notes.append(text)
