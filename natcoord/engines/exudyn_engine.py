"""Exudyn as an engine: redundant (absolute) coordinates, implicit index-3 generalized-alpha.

Every body is a free node (x, y, phi) at its centre of mass; every joint is a constraint,
so loops need no tree. Output is read from Exudyn sensors stored in memory at the case's
output interval.

Conventions handled here (measured with exudyn 1.13.6, see tests/test_engine_exudyn.py):

* ``ObjectJointRevolute2D`` with markers ``[m0, m1]``: its ``Force`` output (world axes) is
  the force on the body of ``m0``; the force on the case's second body is its negative.
* ``ObjectJointPrismatic2D`` is built with markers ``[second body, first body]`` so that the
  normal (``normalMarker1``) turns with the case's first body, as the axis of the case does.
  It has no ``Force`` output: a ``SensorUserFunction`` (called at the output times only)
  reads its first Lagrange multiplier lambda_0, and the force on the case's second body is
  ``+lambda_0`` times the first body's normal (axis turned +90 deg) in world axes.
* A particle that takes part in a prismatic joint needs an orientation marker: it becomes a
  2-D rigid node whose rotation is locked to zero by a ``CoordinateConstraint`` (the locked
  rotation carries no kinetic energy and no reaction force).
* Massless rods are ``ObjectConnectorDistance`` (exact, no substitute): its scalar ``Force``
  output is the axial force, tension positive, whatever the marker order.
* Spring-dampers are ``ObjectConnectorSpringDamper``: its ``Force`` output is the vector
  ``tension * u``, u the unit vector from marker 0 to marker 1 (the ``Displacement``
  output), so the tension is ``Force . u``.
* Redundant constraints (rods closing a loop here, every 3-D case): the Jacobian is
  singular, so the linear solver is ``EigenDense`` with ``ignoreSingularJacobian`` (the
  split of the redundant multipliers is whatever its pivoting picks).
* 3-D cases are built by :mod:`.exudyn_3d`.
"""

from __future__ import annotations

import time

import numpy as np

from ..errors import Unsupported
from ..mechanism import GROUND, Case
from ..result import Motion
from .base import EngineRun, merged, steps_per_sample

NAME = "exudyn"
PACKAGE = "exudyn"
DEFAULTS = {
    "solver": "generalized_alpha",  # implicit, index 3 (the only solver offered here)
    "dt": 1e-3,                     # fixed time step h, s; must divide the output interval
    "spectral_radius": 0.9,         # rho_inf; 1.0 makes reactions noisy (ENGINE-NOTES)
    "newton_rtol": 1e-10,           # Newton relative tolerance (Exudyn default 1e-8)
    "newton_atol": 1e-10,           # Newton absolute tolerance (Exudyn default 1e-10)
    "modified_newton": False,       # full Newton: ~2 iterations a step, faster here than
                                    # Exudyn's default modified Newton (~7 iterations)
    "linear_solver": "auto",        # auto: EigenDense + ignoreSingularJacobian when the
                                    # constraints may be redundant (rods, 3-D), else
                                    # Exudyn's default; or "default" | "singular"
}

J2 = np.array([[0.0, -1.0], [1.0, 0.0]])  # +90 deg rotation


def version() -> str:
    import exudyn

    return exudyn.__version__


def _rot(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


def _v3(v) -> list[float]:
    return [float(v[0]), float(v[1]), 0.0]


def _check(case: Case, s: dict) -> None:
    if case.dimension not in (2, 3):
        raise Unsupported(f"{case.name} is {case.dimension}-D: the Exudyn adapter models "
                          "2-D and 3-D cases")
    drivers = getattr(case, "drivers", ())
    if drivers:
        raise Unsupported(f"driver(s) {', '.join(d.name for d in drivers)}: prescribed "
                          "motions are not modelled by the Exudyn adapter yet")
    if s["solver"] != "generalized_alpha":
        raise Unsupported(f"solver {s['solver']!r}: only 'generalized_alpha' (index 3) is "
                          "offered; the index-2 trapezoidal variants drift by ~h^2")
    if s["linear_solver"] not in ("auto", "default", "singular"):
        raise ValueError(f"linear_solver {s['linear_solver']!r}: 'auto', 'default' or "
                         "'singular'")
    if case.dimension == 3:
        return  # checked by exudyn_3d
    for j in case.joints:
        if j.type not in ("revolute", "prismatic"):
            raise Unsupported(f"joint {j.name}: type {j.type!r} is not modelled in 2-D")
    for f in case.forces:
        if f.type not in ("torque", "force"):
            raise Unsupported(f"force on {f.body}: type {f.type!r} is not modelled")
        if f.type == "torque" and f.body != GROUND and case.body(f.body).kind == "particle":
            raise Unsupported(f"torque on particle {f.body}: a particle has no rotation")


def _failure(mbs, case: Case, n_steps: int, h: float, what: str) -> str:
    """A solver failure message: where it stopped and what Newton reported."""
    msg = f"exudyn: generalized-alpha failed on {case.name} ({what.strip()})"
    solver = getattr(mbs, "sys", {}).get("dynamicSolver")
    if solver is not None:
        it, conv = solver.it, solver.conv
        why = [k for k, v in (("Newton did not converge", not conv.newtonConverged),
                              ("Newton diverged", conv.newtonSolutionDiverged),
                              ("linear solver failed (singular Jacobian)",
                               conv.linearSolverFailed)) if v]
        msg += (f" at t = {it.currentTime:.6g} s, step {it.currentStepIndex} of {n_steps}, "
                f"h = {h:g}, Newton residual {conv.residual:.3g}")
        if why:
            msg += ": " + ", ".join(why)
    return msg


def step_plan(case: Case, s: dict) -> tuple[float, int, int, int]:
    """(step h, steps per sample, samples, steps in all)."""
    h = float(s["dt"])
    k = steps_per_sample(case, h)
    n_samples = len(case.times)
    return h, k, n_samples, k * (n_samples - 1)


def model_notes(case: Case, s: dict, h: float, coordinates: str, *more: str) -> list[str]:
    """The notes every adapter run starts with: its coordinates, the integrator, ``more``
    and the linear solver if the constraints are redundant."""
    notes = [
        coordinates,
        f"implicit generalized-alpha, index 3, rho_inf {s['spectral_radius']}, fixed step "
        f"{h:g} s, Newton rtol {s['newton_rtol']:g}",
        *more,
    ]
    if singular_solver(case, s):
        notes.append("linear solver EigenDense with ignoreSingularJacobian (redundant "
                     "constraints)")
    return notes


def new_system(exu, ei):
    """(system container, its system, the ground object)."""
    SC = exu.SystemContainer()
    mbs = SC.AddSystem()
    return SC, mbs, mbs.AddObject(ei.ObjectGround())


def engine_run(case: Case, s: dict, motion: Motion, outputs, build: float, wall: float,
               solver, n_steps: int, notes: list) -> EngineRun:
    """The run, once every one of ``outputs`` is checked finite."""
    for arr in outputs:
        if not np.all(np.isfinite(arr)):
            raise RuntimeError(f"exudyn: non-finite output on {case.name}")
    it = solver.it
    counters = {"steps": n_steps, "newton_iterations": int(it.newtonStepsCount),
                "jacobians": int(it.newtonJacobiCount)}
    return EngineRun(motion, build, wall, n_steps, s, counters, notes)


def singular_solver(case: Case, s: dict) -> bool:
    """Whether to use EigenDense with ignoreSingularJacobian (redundant constraints)."""
    if s["linear_solver"] == "auto":
        return case.dimension == 3 or bool(case.rods)
    return s["linear_solver"] == "singular"


def solve(exu, mbs, case: Case, s: dict, n_steps: int, h: float):
    """Generalized-alpha over the case's duration with fixed steps; returns (wall time, solver).
    Raises RuntimeError with where and why it failed."""
    sim = exu.SimulationSettings()
    ti = sim.timeIntegration
    ti.startTime, ti.endTime, ti.numberOfSteps = 0.0, float(case.times[-1]), n_steps
    ti.adaptiveStep = False
    ti.automaticStepSize = False
    ti.verboseMode = 0
    ti.generalizedAlpha.spectralRadius = float(s["spectral_radius"])
    ti.generalizedAlpha.useIndex2Constraints = False
    ti.generalizedAlpha.useNewmark = False
    ti.generalizedAlpha.computeInitialAccelerations = True
    ti.newton.relativeTolerance = float(s["newton_rtol"])
    ti.newton.absoluteTolerance = float(s["newton_atol"])
    ti.newton.useModifiedNewton = bool(s["modified_newton"])
    if singular_solver(case, s):
        sim.linearSolver.solverType = exu.LinearSolverType.EigenDense
        sim.linearSolver.ignoreSingularJacobian = True
    sim.solution.file.write = False
    sim.solution.sensors.writePeriod = case.output_dt
    sim.show.computationTime = False
    sim.show.statistics = False

    quiet = exu.config.printToConsole
    exu.config.printToConsole = False
    try:
        t1 = time.perf_counter()
        try:
            ok = mbs.SolveDynamic(sim, storeSolver=True, showHints=False,
                                  showCausingItems=False)
        except Exception as e:  # Exudyn raises when Newton fails, on a singular Jacobian, ...
            raise RuntimeError(_failure(mbs, case, n_steps, h, str(e))) from e
        wall = time.perf_counter() - t1
    finally:
        exu.config.printToConsole = quiet
    if not ok:
        raise RuntimeError(_failure(mbs, case, n_steps, h, "SolveDynamic returned False"))
    return wall, mbs.sys["dynamicSolver"]


def stored(mbs, case: Case, sn: int) -> np.ndarray:
    """A sensor's stored values at the case's sample times, (T, k) without the time column."""
    d = np.asarray(mbs.GetSensorStoredData(sn), float)
    n = len(case.times)
    if d.shape[0] != n or not np.allclose(d[:, 0], case.times, atol=1e-9):
        raise RuntimeError(f"exudyn: sensor samples at {d[:, 0].tolist()[:5]}... do not "
                           f"match the case times ({n} samples)")
    return d[:, 1:]


def connectors(ei, mbs, case: Case, marker, sensor, notes: list[str]) -> dict:
    """Massless rods (ObjectConnectorDistance) and spring-dampers (ObjectConnectorSpringDamper)
    between position markers; returns name -> function(stored) giving the tension (T,)."""
    import exudyn as exu

    OV = exu.OutputVariableType
    out = {}
    for r in case.rods:
        (a, pa), (b, pb) = r.ends
        co = mbs.AddObject(ei.ObjectConnectorDistance(
            markerNumbers=[marker(a, pa), marker(b, pb)], distance=float(r.length)))
        sf = sensor(kind=ei.SensorObject, objectNumber=co, outputVariableType=OV.Force)
        out[r.name] = (lambda get, sf=sf: get(sf)[:, 0])
    for sp in case.springs:
        (a, pa), (b, pb) = sp.ends
        co = mbs.AddObject(ei.ObjectConnectorSpringDamper(
            markerNumbers=[marker(a, pa), marker(b, pb)], referenceLength=float(sp.length),
            stiffness=float(sp.stiffness), damping=float(sp.damping)))
        sf = sensor(kind=ei.SensorObject, objectNumber=co, outputVariableType=OV.Force)
        sd = sensor(kind=ei.SensorObject, objectNumber=co, outputVariableType=OV.Displacement)

        def tension(get, sf=sf, sd=sd):
            d = get(sd)
            return np.sum(get(sf) * d, axis=1) / np.linalg.norm(d, axis=1)
        out[sp.name] = tension
    if case.rods:
        notes.append("massless rods: ObjectConnectorDistance (exact); axial force = its Force "
                     "output (tension positive)")
    if case.springs:
        notes.append("spring-dampers: ObjectConnectorSpringDamper (rest length = distance at "
                     "t = 0); tension = Force output . unit Displacement")
    return out


def run(case: Case, init, settings: dict) -> EngineRun:
    s = merged(DEFAULTS, settings)
    _check(case, s)
    if case.dimension == 3:
        from .exudyn_3d import run3d

        return run3d(case, init, s)
    h, k, n_samples, n_steps = step_plan(case, s)

    import exudyn as exu
    from exudyn import itemInterface as ei

    OV = exu.OutputVariableType
    notes = model_notes(
        case, s, h,
        "redundant absolute coordinates: one NodeRigidBody2D + ObjectRigidBody2D per body at "
        "its centre of mass; every joint is a constraint (no tree)",
        "revolute joints: ObjectJointRevolute2D; reaction = -Force output (Force is the "
        "force on the first marker's body)")

    t0 = time.perf_counter()
    SC, mbs, ground = new_system(exu, ei)

    prismatic_bodies = {b for j in case.joints if j.type == "prismatic" for b in j.bodies}
    nodes, objs, locked = {}, {}, []
    for b in case.bodies:
        st = init[b.name]
        R = _rot(st.angle)
        rc = R @ b.com
        pos = np.asarray(st.origin, float) + rc
        vel = np.asarray(st.velocity, float) + st.omega * (J2 @ rc)
        if b.kind == "particle" and b.name not in prismatic_bodies:
            n = mbs.AddNode(ei.NodePoint2D(referenceCoordinates=[pos[0], pos[1]],
                                           initialCoordinates=[0.0, 0.0],
                                           initialVelocities=[vel[0], vel[1]]))
            o = mbs.AddObject(ei.ObjectMassPoint2D(nodeNumber=n, mass=b.mass))
            notes.append(f"particle {b.name}: NodePoint2D + ObjectMassPoint2D")
        else:
            phi = st.angle if b.kind != "particle" else 0.0
            inertia = b.inertia
            if b.kind == "particle":  # locked rotation: inertia only conditions the matrix
                inertia = b.mass * 1.0 if b.mass > 0 else 1.0
                locked.append(b.name)
            n = mbs.AddNode(ei.NodeRigidBody2D(
                referenceCoordinates=[pos[0], pos[1], phi], initialCoordinates=[0.0, 0.0, 0.0],
                initialVelocities=[vel[0], vel[1], st.omega if b.kind != "particle" else 0.0]))
            o = mbs.AddObject(ei.ObjectRigidBody2D(nodeNumber=n, mass=b.mass, inertia=inertia))
        nodes[b.name], objs[b.name] = n, o
        if np.any(case.gravity != 0):
            mm = mbs.AddMarker(ei.MarkerBodyMass(bodyNumber=o))
            mbs.AddLoad(ei.LoadMassProportional(markerNumber=mm,
                                                loadVector=_v3(case.gravity)))
    if locked:
        gn = mbs.AddNode(ei.NodePointGround(referenceCoordinates=[0.0, 0.0, 0.0]))
        gm = mbs.AddMarker(ei.MarkerNodeCoordinate(nodeNumber=gn, coordinate=0))
        for name in locked:
            rm = mbs.AddMarker(ei.MarkerNodeCoordinate(nodeNumber=nodes[name], coordinate=2))
            mbs.AddObject(ei.CoordinateConstraint(markerNumbers=[gm, rm]))
        notes.append(f"particle(s) {', '.join(locked)} in a prismatic joint: rigid 2-D node "
                     "with rotation locked to 0 (a prismatic joint needs orientation markers)")

    def marker(body: str, point: str, rigid: bool = False):
        kind = ei.MarkerBodyRigid if rigid else ei.MarkerBodyPosition
        if body == GROUND:
            return mbs.AddMarker(kind(bodyNumber=ground, localPosition=_v3(case.ground[point])))
        b = case.body(body)
        return mbs.AddMarker(kind(bodyNumber=objs[body],
                                  localPosition=_v3(b.points[point] - b.com)))

    for f in case.forces:
        if f.body == GROUND:
            continue
        if f.type == "torque":
            mr = mbs.AddMarker(ei.MarkerBodyRigid(bodyNumber=objs[f.body]))
            mbs.AddLoad(ei.LoadTorqueVector(markerNumber=mr,
                                            loadVector=[0.0, 0.0, float(f.value)]))
        else:  # world force at a body point
            mbs.AddLoad(ei.LoadForceVector(markerNumber=marker(f.body, f.point),
                                           loadVector=_v3(f.value)))

    def angle0(body: str) -> float:
        if body == GROUND or case.body(body).kind == "particle":
            return 0.0
        return float(init[body].angle)

    force_sign, joint_objs = {}, {}
    for j in case.joints:
        a, b = j.bodies
        pa, pb = j.points
        if j.type == "revolute":
            jo = mbs.AddObject(ei.ObjectJointRevolute2D(
                markerNumbers=[marker(a, pa, False), marker(b, pb, False)]))
            force_sign[j.name] = -1.0
        else:
            # markers [b, a]: normalMarker1 lives in a's frame, like the case's axis
            axis = np.asarray(j.axis, float) / np.linalg.norm(j.axis)
            rel = _rot(angle0(a) - angle0(b))  # a's frame -> b's frame at the start
            b_rigid = case.body(b).kind != "particle" if b != GROUND else True
            jo = mbs.AddObject(ei.ObjectJointPrismatic2D(
                markerNumbers=[marker(b, pb, True), marker(a, pa, True)],
                axisMarker0=_v3(rel @ axis), normalMarker1=_v3(J2 @ axis),
                constrainRotation=bool(b_rigid)))
            force_sign[j.name] = 1.0
        joint_objs[j.name] = jo
    if any(j.type == "prismatic" for j in case.joints):
        notes.append("prismatic joints: ObjectJointPrismatic2D with markers [second, first] "
                     "so the normal turns with the first body; reaction = +lambda_0 times the "
                     "normal (the joint has no Force output; lambda_0 read by a sensor user "
                     "function at the output times); its moment is not reported")

    def sensor(**kw):
        return mbs.AddSensor(kw.pop("kind")(storeInternal=True, writeToFile=False, **kw))

    tensions = connectors(ei, mbs, case, marker, sensor, notes)

    sens = {}
    for b in case.bodies:
        n = nodes[b.name]
        sens[b.name] = [sensor(kind=ei.SensorNode, nodeNumber=n, outputVariableType=v)
                        for v in (OV.Position, OV.Velocity)]
        if b.kind != "particle":
            sens[b.name] += [sensor(kind=ei.SensorNode, nodeNumber=n, outputVariableType=v)
                             for v in (OV.Rotation, OV.AngularVelocity)]
    ae_index: dict[str, int] = {}  # first Lagrange multiplier of each prismatic joint

    def lagrange(name: str):
        def f(mbs_, t, sensor_numbers, factors, configuration):
            return [mbs_.systemData.GetAECoordinates(configuration)[ae_index[name]]]
        return f

    jsens = {}
    for j in case.joints:
        if j.type == "revolute":
            jsens[j.name] = sensor(kind=ei.SensorObject, objectNumber=joint_objs[j.name],
                                   outputVariableType=OV.Force)
        else:  # ObjectJointPrismatic2D has no Force output: read its multiplier lambda_0
            jsens[j.name] = sensor(kind=ei.SensorUserFunction,
                                   sensorUserFunction=lagrange(j.name))

    mbs.Assemble()
    for j in case.joints:
        if j.type == "prismatic":
            ae_index[j.name] = int(mbs.systemData.GetObjectLTGAE(joint_objs[j.name])[0])
    build = time.perf_counter() - t0

    wall, solver = solve(exu, mbs, case, s, n_steps, h)

    def get(sn: int) -> np.ndarray:
        return stored(mbs, case, sn)

    origin, angle, velocity, omega = {}, {}, {}, {}
    z = np.zeros(n_samples)
    for b in case.bodies:
        ss = sens[b.name]
        pc, vc = get(ss[0])[:, :2], get(ss[1])[:, :2]
        if b.kind == "particle":
            phi, w = z.copy(), z.copy()
        else:
            phi, w = get(ss[2])[:, 2], get(ss[3])[:, 2]
        c, si = np.cos(phi), np.sin(phi)
        rc = np.stack([c * b.com[0] - si * b.com[1], si * b.com[0] + c * b.com[1]], -1)
        origin[b.name] = pc - rc
        velocity[b.name] = vc - w[:, None] * np.stack([-rc[:, 1], rc[:, 0]], -1)
        angle[b.name], omega[b.name] = phi, w
    forces = {}
    for j in case.joints:
        if j.type == "revolute":
            forces[j.name] = force_sign[j.name] * get(jsens[j.name])[:, :2]
        else:  # force on the second body = sign * lambda_0 * (normal of the first body)
            lam = get(jsens[j.name])[:, 0]
            a = j.bodies[0]
            phi = angle[a] if a != GROUND else z
            u = np.asarray(j.axis, float) / np.linalg.norm(j.axis)
            c, si = np.cos(phi), np.sin(phi)
            n = np.stack([-(si * u[0] + c * u[1]), c * u[0] - si * u[1]], -1)
            forces[j.name] = force_sign[j.name] * lam[:, None] * n
    rod_force = {name: f(get) for name, f in tensions.items()}

    m = Motion(case.times.copy(), origin, angle, velocity, omega, forces, rod_force=rod_force)
    return engine_run(case, s, m, (*origin.values(), *angle.values(), *forces.values(),
                                   *rod_force.values()), build, wall, solver, n_steps, notes)
