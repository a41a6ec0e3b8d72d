"""Exudyn's time integration and its output: the step plan, generalized-alpha, the stored
sensor samples and the run record. Knows nothing of bodies or joints."""

from __future__ import annotations

import time

import numpy as np

from ...case.mechanism import Case
from ...outputs.result import Motion
from ..base import EngineRun, steps_per_sample


def step_plan(case: Case, s: dict) -> tuple[float, int]:
    """(fixed step h in s, number of steps over the case's duration)."""
    h = float(s["dt"])
    k = steps_per_sample(case, h)  # raises ValueError when h does not divide the interval
    return h, k * (len(case.times) - 1)


def singular_solver(case: Case, s: dict) -> bool:
    """Whether to use EigenDense with ignoreSingularJacobian (redundant constraints)."""
    if s["linear_solver"] == "auto":
        return case.dimension == 3 or bool(case.rods)
    return s["linear_solver"] == "singular"


def integrator_notes(case: Case, s: dict, h: float) -> list[str]:
    """The integrator's note and, if the constraints may be redundant, the linear solver's."""
    notes = [f"implicit generalized-alpha, index 3, rho_inf {s['spectral_radius']}, fixed step "
             f"{h:g} s, Newton rtol {s['newton_rtol']:g}"]
    if singular_solver(case, s):
        notes.append("linear solver EigenDense with ignoreSingularJacobian (redundant "
                     "constraints)")
    elif s["linear_solver"] == "sparse":
        notes.append("linear solver EigenSparse")
    return notes


def _settings(exu, case: Case, s: dict, n_steps: int):
    """Exudyn's SimulationSettings for fixed-step index-3 generalized-alpha, quiet, with the
    sensors stored in memory at the case's output interval."""
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
    elif s["linear_solver"] == "sparse":  # many bodies: the dense LU costs O(n^3) a Jacobian
        sim.linearSolver.solverType = exu.LinearSolverType.EigenSparse
    sim.solution.file.write = False
    sim.solution.sensors.writePeriod = case.output_dt
    sim.show.computationTime = False
    sim.show.statistics = False
    return sim


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


def solve(exu, mbs, case: Case, s: dict, n_steps: int, h: float):
    """Generalized-alpha over the case's duration with fixed steps; returns (wall time s,
    solver). Raises RuntimeError with where and why it failed."""
    sim = _settings(exu, case, s, n_steps)
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


def engine_run(case: Case, s: dict, motion: Motion, build: float, wall: float, solver,
               n_steps: int, notes: list[str]) -> EngineRun:
    """The run, once every output array of ``motion`` is checked finite."""
    outputs = (*motion.origin.values(), *motion.angle.values(), *motion.rotation.values(),
               *motion.joint_force.values(), *motion.rod_force.values(),
               *motion.driver_effort.values())
    for arr in outputs:
        if not np.all(np.isfinite(arr)):
            raise RuntimeError(f"exudyn: non-finite output on {case.name}")
    it = solver.it
    counters = {"steps": n_steps, "newton_iterations": int(it.newtonStepsCount),
                "jacobians": int(it.newtonJacobiCount)}
    return EngineRun(motion, build, wall, n_steps, s, counters, notes)
