"""Start, integrate and sample a built model: the t = 0 state (coordinates 0, speeds from the
case's rates), OpenSim's Manager driving a Simbody integrator to every sample time, and the
3-D samples (bodies, joint forces, rod and spring tensions, driver efforts)."""

from __future__ import annotations

import time

import numpy as np

from .model import Built

INTEGRATORS = {  # settings name -> Manager.IntegratorMethod attribute
    "rk_merson": "IntegratorMethod_RungeKuttaMerson",
    "rk_feldberg": "IntegratorMethod_RungeKuttaFeldberg",
    "rk3": "IntegratorMethod_RungeKutta3",
    "rk2": "IntegratorMethod_RungeKutta2",
    "semi_explicit_euler2": "IntegratorMethod_SemiExplicitEuler2",
    "verlet": "IntegratorMethod_Verlet",
    "cpodes": "IntegratorMethod_CPodes",
    "explicit_euler": "IntegratorMethod_ExplicitEuler",
}


def np3(v) -> np.ndarray:
    return np.array([v.get(0), v.get(1), v.get(2)])


def initial_state(osim, b: Built, velocity_check: float):
    """The t = 0 state: every coordinate 0, speeds from the t = 0 frames; checked against
    them (raises when a body's velocity is off by more than ``velocity_check``)."""
    state = b.model.initSystem()
    for oj, rates in b.speeds:
        for k, r in enumerate(rates):
            # a prescribed coordinate too: its u is only overwritten when the integrator
            # starts, and the check below reads the state as set here
            oj.get_coordinates(k).setSpeedValue(state, float(r))
    b.model.realizeVelocity(state)
    for name, ob in b.bodies.items():
        F = b.frames[name]
        Vg = ob.getVelocityInGround(state)
        w = np3(Vg.get(0))
        v = np3(Vg.get(1))
        err = max(np.max(np.abs(w - F.omega)), np.max(np.abs(v - F.velocity)))
        pos = np.max(np.abs(np3(ob.getPositionInGround(state)) - F.origin))
        if err > velocity_check or pos > 1e-9:
            raise RuntimeError(f"simbody: body {name!r} starts {pos:.3g} m, {err:.3g} m/s or "
                               "rad/s away from natcoord's initial state")
    return state


def integrate(osim, b: Built, state, times: np.ndarray, s: dict):
    """Yield the state at every sample time (the first is ``state`` realized), and finally
    the integrator's counters as a dict: ``steps`` and ``stepping_time_s`` (s, the
    Manager's initialize and integrate calls alone, not the readout the consumer does
    between two yields)."""
    method = str(s["integrator"]).lower()
    if method not in INTEGRATORS:
        raise ValueError(f"simbody: unknown integrator {s['integrator']!r} "
                         f"({' | '.join(INTEGRATORS)})")
    manager = osim.Manager(b.model)
    manager.setIntegratorMethod(getattr(osim.Manager, INTEGRATORS[method]))
    if s.get("dt"):  # fixed-step integrators (explicit_euler, rk2, ...)
        manager.setIntegratorFixedStepSize(float(s["dt"]))
    else:
        manager.setIntegratorAccuracy(float(s["accuracy"]))
    manager.setIntegratorConstraintTolerance(float(s["constraint_tolerance"]))
    manager.setIntegratorInternalStepLimit(int(s["step_limit"]))
    manager.setIntegratorMinimumStepSize(float(s["min_step"]))
    # the Python bindings do not wrap the Integrator (no step counts); the Manager's state
    # storage (in memory) gets one row of state values per internal step, so its length
    # counts the steps. Not its states trajectory: that copies the whole State every step
    # (about 400 us/step on slider_crank) and again when read back (0.45 s)
    manager.setWriteToStorage(True)
    manager.setRecordStatesTrajectory(False)
    manager.setPerformAnalyses(False)
    state.setTime(float(times[0]))
    t0 = time.perf_counter()
    manager.initialize(state)
    stepping = time.perf_counter() - t0
    yield manager.getState()
    for t in times[1:]:
        # the returned state is the Manager's own, overwritten by the next call: the
        # consumer reads it out before asking for the next one, off the clock
        t0 = time.perf_counter()
        now = manager.integrate(float(t))
        stepping += time.perf_counter() - t0
        yield now
    yield {"steps": int(manager.getStateStorage().getSize()) - 1,
           "stepping_time_s": stepping}


def _point_state(ob, state, p: np.ndarray):
    """World position and velocity (3,) of body point p (body frame), OpenSim body or
    ground."""
    X = ob.getTransformInGround(state)
    R = X.R().asMat33()
    Rm = np.array([[R.get(i, j) for j in range(3)] for i in range(3)])
    V = ob.getVelocityInGround(state)
    w, v0 = np3(V.get(0)), np3(V.get(1))
    r = Rm @ p
    return np3(X.p()) + r, v0 + np.cross(w, r)


def sample(osim, b: Built, states, T: int):
    """3-D samples at every state: (origin, rotation, velocity, omega, acceleration, alpha,
    forces, rod_force, driver_effort, counters, drift), as
    :func:`natcoord.engines.planar.drop` takes them; drift (2,): the largest constraint
    violation of positions and speeds seen."""
    case = b.case
    names = list(b.bodies)
    origin = {n: np.empty((T, 3)) for n in names}
    rotation = {n: np.empty((T, 3, 3)) for n in names}
    velocity = {n: np.empty((T, 3)) for n in names}
    omega = {n: np.empty((T, 3)) for n in names}
    accel = {n: np.empty((T, 3)) for n in names}
    alpha = {n: np.empty((T, 3)) for n in names}
    forces = {j.name: np.empty((T, 3)) for j in case.joints}
    rod_force = {x.name: np.empty(T) for x in case.rods} | {x.name: np.empty(T)
                                                            for x in case.springs}
    effort = {d.name: np.empty(T) for d, _, _ in b.drivers}
    model = b.model
    ground = model.getGround()
    drift = np.zeros(2)
    it = iter(states)
    for i in range(T):
        state = next(it)
        model.realizeAcceleration(state)
        drift = np.maximum(drift, [_inf_norm(state.getQErr()), _inf_norm(state.getUErr())])
        for n in names:
            ob = b.bodies[n]
            X = ob.getTransformInGround(state)
            R = X.R().asMat33()
            rotation[n][i] = [[R.get(r, c) for c in range(3)] for r in range(3)]
            origin[n][i] = np3(X.p())
            V = ob.getVelocityInGround(state)
            omega[n][i], velocity[n][i] = np3(V.get(0)), np3(V.get(1))
            A = ob.getAccelerationInGround(state)
            alpha[n][i], accel[n][i] = np3(A.get(0)), np3(A.get(1))
        for j, oj, sign in b.tree:
            forces[j.name][i] = sign * np3(oj.calcReactionOnChildExpressedInGround(state)
                                           .get(1))
        for j, _con, _a, _c in b.loops:
            forces[j.name][i] = 0.0
        for j, con, _a, _c in b.loops:  # a revolute held at two axis points: the sum
            forces[j.name][i] += _constraint_force(osim, con, state, 1)
        for rod, con, n1, r1, n2, r2 in b.rods:
            f2 = _constraint_force(osim, con, state, 1)
            p1, _ = _point_state(_body(b, ground, n1), state, r1)
            p2, _ = _point_state(_body(b, ground, n2), state, r2)
            e = (p1 - p2) / np.linalg.norm(p1 - p2)
            rod_force[rod.name][i] = f2 @ e  # tension pulls the second end towards the first
        for sp, n1, r1, n2, r2 in b.springs:
            p1, v1 = _point_state(_body(b, ground, n1), state, r1)
            p2, v2 = _point_state(_body(b, ground, n2), state, r2)
            d = np.linalg.norm(p1 - p2)
            e = (p1 - p2) / d
            rod_force[sp.name][i] = sp.stiffness * (d - sp.length) + sp.damping * (e @ (v1 - v2))
        for d, oj, sign in b.drivers:
            # the mobilizer reaction carries the prescribed motion's effort along its axis
            # (the joint frame's Z for a pin, X for a slider, moving with the child)
            Rc = oj.getChildFrame().getTransformInGround(state).R().asMat33()
            reac = oj.calcReactionOnChildExpressedInGround(state)
            if d.type == "angle":
                axis, load = [Rc.get(r, 2) for r in range(3)], np3(reac.get(0))
            else:
                axis, load = [Rc.get(r, 0) for r in range(3)], np3(reac.get(1))
            effort[d.name][i] = sign * (load @ np.asarray(axis))
    counters = next(it)
    return (origin, rotation, velocity, omega, accel, alpha, forces, rod_force, effort, counters,
            drift)


def _inf_norm(v) -> float:
    return float(np.max(np.abs(v.to_numpy()))) if v.size() else 0.0


def _body(b: Built, ground, node: str):
    return ground if node == "ground" else b.bodies[node]


def _constraint_force(osim, con, state, k: int) -> np.ndarray:
    """The force (3,) N, world axes, that constraint ``con`` applies to its ``k``-th body (0
    or 1, the order it was given; ground included). ``calcConstraintForces`` fills one
    spatial vector [moment, force] per constrained body in that order, in ground axes, with
    Simbody's multiplier sign: minus the force applied (checked on a pendulum hung by a
    PointConstraint, either order)."""
    bf = osim.VectorOfSpatialVec()
    con.calcConstraintForces(state, bf, osim.Vector())
    return -np3(bf.get(k).get(1))
