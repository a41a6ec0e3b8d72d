"""Stepping a DART world and reading it at the case's sample times: body frames, reactions
(tree joints from DART's joint wrenches, loop joints by Newton-Euler), light-rod and spring
forces, driver efforts. All arrays are 3-D (:func:`natcoord.engines.planar.drop` takes
them to the case's dimension)."""

from __future__ import annotations

import time

import numpy as np

from ...case.mechanism import GROUND, Case
from ..planar import node_point


def make_world(dart, skel, gravity: np.ndarray, dt: float):
    """A DART world (gravity (3,) m/s^2, time step dt s) holding ``skel``; returns (world,
    its constraint solver)."""
    world = dart.simulation.World()
    world.setGravity(gravity)
    world.setTimeStep(dt)
    world.addSkeleton(skel)
    return world, world.getConstraintSolver()


def loop_bodies(loops, rods, notes: list) -> dict[str, tuple[str, int]]:
    """Loop joint -> (body only it closes, sign): its force by that body's Newton-Euler
    balance (rod ends count as closing); notes the joints without one."""
    closing: dict[str, int] = {}
    for x in [b for j in loops for b in j.bodies] + [r.ends[1][0] for r in rods]:
        closing[x] = closing.get(x, 0) + 1
    loop_body: dict[str, tuple[str, int]] = {}
    for j in loops:
        for x, sg in ((j.bodies[1], 1), (j.bodies[0], -1)):
            if x != GROUND and closing[x] == 1:
                loop_body[j.name] = (x, sg)
                break
        else:
            notes.append(f"loop joint {j.name!r}: no body closed by it alone; its force is "
                         "not reported")
    if loop_body:
        notes.append("loop-joint force(s) " + ", ".join(loop_body) + " from the Newton-Euler "
                     "balance of the body (DART does not expose constraint impulses)")
    return loop_body


def simulate_with_erp(dart, s: dict, notes: list, dt: float, extrapolated: bool, simulate):
    """``simulate()`` with the settings' error reduction on every joint constraint (a
    process-wide DART static, restored afterwards), and the integrator's note."""
    JC = dart.constraint.DynamicJointConstraint  # statics of Ball/Weld/RevoluteJointConstraint
    saved = (JC.getErrorReductionParameter(), JC.getMaxErrorReductionVelocity())
    JC.setErrorReductionParameter(float(s["erp"]))
    JC.setMaxErrorReductionVelocity(float(s["max_error_reduction_velocity"]))
    try:
        result = simulate()
    finally:
        JC.setErrorReductionParameter(saved[0])
        JC.setMaxErrorReductionVelocity(saved[1])
    notes.append(f"semi-implicit Euler (DART's only integrator, first order), dt {dt:g} s; "
                 "reactions and accelerations are those of the step starting at each sample "
                 "time" + (", at t = 0 extrapolated from steps 2 and 3 (the first two steps "
                           "of a loop constraint are transients)" if extrapolated else ""))
    return result


def stepper(world, before_step):
    """``steps(n)``: n world steps, ``before_step()`` ahead of each (DART clears external
    forces and commands after every step); wall time (s) and count in the returned clock."""
    clock = {"wall": 0.0, "steps": 0}

    def steps(n):
        t0 = time.perf_counter()
        for _ in range(n):
            before_step()
            world.step()
        clock["wall"] += time.perf_counter() - t0
        clock["steps"] += n

    return steps, clock


def step_and_read(skel, steps, read) -> dict:
    """One step; ``read()`` of the reactions it carries, at the state it started from
    (accelerations stay (v1 - v0) / dt as DART left them); then on from the step's end."""
    q, qd = skel.getPositions(), skel.getVelocities()
    steps(1)
    q1, qd1 = skel.getPositions(), skel.getVelocities()
    skel.setPositions(q)
    skel.setVelocities(qd)
    out = read()
    skel.setPositions(q1)
    skel.setVelocities(qd1)
    return out


def check_state(skel, world, t: float) -> None:
    """DART only warns on a singular step and carries on: a non-finite state fails the run."""
    q, qd = skel.getPositions(), skel.getVelocities()
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
        raise RuntimeError(f"DART diverged: NaN/inf state at t = {t:.4g} s "
                           f"(dt {world.getTimeStep():g} s)")


def check_drift(drift: float, max_drift: float, t: float) -> None:
    if drift > max_drift or not np.isfinite(drift):
        raise RuntimeError(f"DART diverged: loop joint gap {drift:.3g} m exceeds "
                           f"{max_drift:g} m by t = {t:.4g} s")


def sample_reactions(read, extrapolate: bool) -> tuple[dict, int]:
    """The reactions at a sample and the steps taken: with loops and a moving start, the
    first two steps' reactions are off by O(1) (step 0 enforces the loop at velocity level
    only: it misses the J_dot v part, the error-reduction term that supplies it later is still
    zero; step 1 overshoots by about half that), so at t = 0 (``extrapolate``) they are
    extrapolated linearly from steps 2 and 3 (exact at rest to O(dt^2))."""
    f = read()
    if not extrapolate:
        return f, 1
    read()
    f2, f3 = read(), read()
    return {name: 3 * f2[name] - 2 * f3[name] for name in f}, 4


class Sampler:
    """Reads the skeleton: body frames at a sample, and the reactions of the step just
    taken (joint forces (3,) N on the joint's second body, accelerations, rod tensions,
    driver efforts)."""

    def __init__(self, dart, case: Case, sk, loop_body, drivers, loads):
        self.W = dart.dynamics.Frame.World()
        self.case, self.sk, self.loop_body, self.drivers = case, sk, loop_body, drivers
        self.resultant = loads[1]
        self.g = np.asarray(case.gravity, float)
        self.names = [b.name for b in case.bodies]
        # a particle's frame follows its point: that point's motion, angle 0
        self.particle = {b.name: next(iter(b.points.values())) for b in case.bodies
                         if b.kind == "particle"}
        self.loop_pts = [(j.bodies, [node_point(case, b, p) for b, p in
                                     zip(j.bodies, j.points, strict=True)])
                         for j in sk.loops]

    def frames(self) -> dict[str, tuple]:
        """body -> (origin, R, velocity, omega) now, world axes."""
        W, out = self.W, {}
        for n in self.names:
            node = self.sk.nodes[n]
            M = node.getWorldTransform().matrix()
            if n in self.particle:
                p = self.particle[n]
                out[n] = (M[:3, :3] @ p + M[:3, 3] - p, np.eye(3),
                          np.asarray(node.getLinearVelocity(p, W, W)), np.zeros(3))
            else:
                out[n] = (M[:3, 3], M[:3, :3], np.asarray(node.getLinearVelocity(W, W)),
                          np.asarray(node.getAngularVelocity(W, W)))
        return out

    def drift(self) -> float:
        """The largest gap (m) of a loop joint or a light rod's far end now."""
        def at(body, p):
            if body == GROUND:
                return p
            M = self.sk.nodes[body].getWorldTransform().matrix()
            return M[:3, :3] @ p + M[:3, 3]

        gaps = [np.linalg.norm(at(a, pa) - at(b, pb)) for (a, b), (pa, pb) in self.loop_pts]
        gaps += [r.gap(self.sk.nodes) for r in self.sk.rods]
        return float(max(gaps, default=0.0))

    def reactions(self) -> dict:
        """What the step just taken carries, read at the state it started from."""
        W, sk, out = self.W, self.sk, {}
        Fp = {n: np.asarray(sk.nodes[n].getParentJoint().getWrenchToParentBodyNode(W))[3:]
              for n in self.names}
        for name, joint in sk.joints.items():
            out[name] = sk.sign[name] * Fp[joint.getChildBodyNode().getName()]
        for n in self.names:  # the step's (discrete) accelerations, same instant
            node = sk.nodes[n]
            if n in self.particle:
                out["acc:" + n] = np.asarray(node.getLinearAcceleration(self.particle[n], W, W))
                out["alpha:" + n] = np.zeros(3)
            else:
                out["acc:" + n] = np.asarray(node.getLinearAcceleration(W, W))
                out["alpha:" + n] = np.asarray(node.getAngularAcceleration(W, W))
        for name, (b, sg) in self.loop_body.items():
            # F_loop = m a_G - m g - F_parent - F_applied + sum F_children
            node = sk.nodes[b]
            a = np.asarray(node.getCOMLinearAcceleration(W, W))
            f = node.getMass() * (a - self.g) - Fp[b] - self.resultant(node)
            for cj in sk.children.get(b, []):
                f = f + np.asarray(cj.getWrenchToParentBodyNode(W))[3:]
            out[name] = sg * f
        for r in sk.rods:
            out["rod:" + r.name] = r.tension(W, self.g)
        for d in self.drivers:
            out["driver:" + d.d.name] = d.effort(W)
        return out


def simulate(case: Case, world, sk, sampler: Sampler, steps, clock, spring_forces, k: int,
             max_drift: float, extrapolate0: bool):
    """Step through ``case.times`` (k steps per sample): 3-D samples ``s[kind][body]``,
    joint forces, axial forces, driver efforts and the counters."""
    T = len(case.times)
    kinds = ("origin", "R", "velocity", "omega", "acceleration", "alpha")
    s = {kind: {n: np.zeros((T, 3, 3) if kind == "R" else (T, 3)) for n in sampler.names}
         for kind in kinds}
    force = {name: np.zeros((T, 3)) for name in list(sk.joints) + list(sampler.loop_body)}
    axial = {x.name: np.zeros(T) for x in list(sk.rods) + list(case.springs)}
    effort = {d.d.name: np.zeros(T) for d in sampler.drivers}
    drift = 0.0
    for i, t in enumerate(case.times):
        check_state(sk.skel, world, t)
        for n, fr in sampler.frames().items():
            for kind, x in zip(kinds, fr, strict=False):
                s[kind][n][i] = x
        drift = max(drift, sampler.drift())
        check_drift(drift, max_drift, t)
        for sp, tension in zip(case.springs, spring_forces(), strict=True):
            axial[sp.name][i] = tension
        # the step that starts here carries the reactions of this instant
        f, done = sample_reactions(lambda: step_and_read(sk.skel, steps, sampler.reactions),
                                   i == 0 and extrapolate0)
        for name in force:
            force[name][i] = f[name]
        for r in sk.rods:
            axial[r.name][i] = f["rod:" + r.name]
        for name in effort:
            effort[name][i] = f["driver:" + name]
        for n in sampler.names:
            s["acceleration"][n][i], s["alpha"][n][i] = f["acc:" + n], f["alpha:" + n]
        if i + 1 < T:
            steps(k - done)
    for name, x in list(force.items()) + list(axial.items()) + list(effort.items()):
        if not np.all(np.isfinite(x)):
            raise RuntimeError(f"DART returned a non-finite force for {name!r}")
    counters = {"steps": clock["steps"], "loop_drift_max_m": float(drift)}
    return s, force, axial, effort, counters
