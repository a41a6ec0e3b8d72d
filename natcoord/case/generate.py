"""Case files of parametric benchmark families, written as TOML text (data only).

``natcoord generate <family> --n N --out FILE`` writes one member of a family; the family
functions here return its text, so that a test can compare them with committed files.

Families:

``n_four_bar``  IFToMM A02, the N-four-bar: N + 1 cranks and N couplers.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from ..errors import CaseError, NatcoordError

OUTPUT_DT = 0.01  # s: the output step of every generated or imported case

# Engine settings and tolerances measured for the specification's members (N = 2 for 10 s,
# N = 40 for 20 s), by `natcoord run` against the stored reference (which equals the exact
# one-equation solution, tests/test_catalog_a01_a02.py). Other N get these settings and no
# tolerances: the gate refuses to judge them (exit 2) until they are measured.
# natcoord's for other N: every body its own points (M block-diagonal, so W = J M^-1 J^T
# is banded along the chain: the envelope Cholesky, 4 entries a row, costs linearly in N;
# shared points couple M along the whole chain, M^-1 and W are dense, ~N^2 a step) and
# fixed RK4 steps of 1 ms projected to round-off (adaptive dop853 on these coordinates
# stalls at a singular pass from N = 64: step-size underflow at t = 2.69 s at rtol 5e-12,
# 4.65 s at 1e-12). Measured over 10 s (10 singular passes) against the exact reduction:
# B0 1.39e-9 m (N = 8), 1.37e-9 (16), 1.33e-9 (64), 1.25e-9 (512); at N = 8 h 1.5 ms
# 7.6e-9 m, 2 ms 3.8e-8 m.
N_FOUR_BAR_LINEAR = ('{ coordinates = "joints", method = "rk4", h = 1e-3, linsolve = '
                     '"schur", project_tol = 1e-14, reference = { method = "rk4", h = 5e-4, '
                     'linsolve = "schur", project_tol = 1e-14 }, reference_check = { '
                     'method = "rk4", h = 1e-3, linsolve = "schur", project_tol = 1e-14 } }')
N_FOUR_BAR_ENGINES: dict[str, dict[str, str]] = {
    "natcoord": {"settings": N_FOUR_BAR_LINEAR},
    "mujoco": {"settings": "{ dt = 1e-4, solref_steps = 10 }"},
    "pinocchio": {"settings": "{ dt = 1e-3, mu = 1e-8 }"},
    "exudyn": {"settings": "{ dt = 1e-3 }"},
    "dart": {"settings": "{ dt = 1e-4, erp = 1.0, loop_constraint = \"ball\" }"},
    "simbody": {"settings": "{}"},
    "drake": {"settings": "{ dt = 5e-4 }"},
    "pybullet": {"settings": "{ dt = 1e-4 }"},
}
N_FOUR_BAR_MEASURED: dict[int, dict[str, dict[str, str]]] = {2: {
    "natcoord": {
        "settings": '{ coordinates = "shared", method = "dop853", linsolve = "schur", '
                    'rtol = 5e-12, atol = 1e-14, project_tol = 1e-14, reference = { '
                    'method = "dop853", linsolve = "schur", rtol = 1e-12, atol = 1e-14, '
                    'project_tol = 1e-14 }, reference_check = { method = "dop853", '
                    'linsolve = "schur", rtol = 5e-12, atol = 1e-14, project_tol = 1e-14 } }',
        "tolerance": "{ position = 5e-8, velocity = 2.5e-7, energy = 1e-7 }",
        "reason": "the shared points of the natural coordinates, index-1 Schur path, dop853 "
                  "rtol 5e-12, atol 1e-14, projection to 1e-14 m with Phi summed in two "
                  "doubles (as N = 40). Against the exact one-equation solution: B0 3.7e-9 m "
                  "over 10 s (10 singular passes) under the OpenBLAS kernels Haswell, Zen, "
                  "Sandybridge and Prescott (the same to the last digit); 5.2e-9 m under "
                  "SkylakeX (the default on an AVX-512 processor), whose initial velocities "
                  "differ from theirs in the last bit. (Before a step's end was always "
                  "projected from a factorization at it, November 2026, it was 4.4e-10 and "
                  "2.2e-8 m: the end of a step with output samples inside took the dense "
                  "output's last factorization, so the motion moved with the output times.) "
                  "The singular passes amplify round-off: a change of one ulp in one initial "
                  "velocity gives 3.8e-9 to 1.8e-8 m, 2.0e-8 to 9.4e-8 m/s and 1.9e-9 to "
                  "1.6e-8 J (40 draws under Haswell and 40 under SkylakeX); over rtol 1e-10 "
                  "to 1e-12 under both, 1.1e-9 m (rtol 1e-11) to 2.2e-7 m (rtol 2e-11, "
                  "Haswell; 3.5e-8 under SkylakeX). The former pivoted-QR "
                  "settings (plain sums of Phi, projected to 1e-14 m) stopped with a step-size "
                  "underflow at a singular pass under 4 of 6 kernels and at 5 of 7 rtols: a "
                  "state that far off the manifold meets a hyperbola instead of the branch "
                  "crossing. The reference runs at rtol 1e-12, its check at 5e-12. Tolerances "
                  "~2x the largest error of the one-ulp draws at the case settings",
    },
    "mujoco": {
        "tolerance": "{ position = 1e-3, velocity = 7e-3, energy = 4e-4 }",
        "reason": "RK4 dt 1e-4, loops closed by connect equalities "
                  "(solref 10 dt, solimp 0.9999): measured 3.3e-4 m, 2.3e-3 m/s, "
                  "energy 1.2e-4 J (drift -1.2e-4 J), the soft loops at the singular passes; "
                  "~6 s; x3",
    },
    "pinocchio": {
        "unsupported": "constraintDynamics (RK4 dt 1e-3, mu 1e-8) returns a non-finite "
                       "acceleration at t = 3.18 s, at the singular horizontal position "
                       "where the loop constraints lose rank N",
    },
    "exudyn": {
        "tolerance": "{ position = 4e-4, velocity = 3e-3, energy = 2.5e-3 }",
        "reason": "generalized-alpha rho_inf 0.9, index 3, h 1e-3: measured 1.9e-4 m, "
                  "1.3e-3 m/s, energy 1.2e-3 J (drift -2.3e-6 J over the run); ~1 s; ~2x",
    },
    "dart": {
        "tolerance": "{ position = 1e-6, velocity = 1.2e-3, energy = 2e-2 }",
        "reason": "semi-implicit Euler dt 1e-4, ERP 1.0, ball-joint loop constraints: "
                  "measured 3.6e-7 m, 5.7e-4 m/s, energy 9.1e-3 J (spread 1.8e-2 J, drift "
                  "-8.5e-4 J: first order, symplectic); ~3 s; ~2x",
    },
    "simbody": {
        "settings": "{ accuracy = 5e-8 }",
        "tolerance": "{ position = 3e-5, velocity = 2e-4, energy = 1e-5 }",
        "reason": "Simbody 3.9 (OpenSim 4.6 wheel): PinJoints, loops B1c0 and B2c1 closed by "
                  "PointConstraint; RK-Merson at accuracy 5e-8 takes one step per 0.01 s "
                  "output interval (1002 steps): measured 2.2e-6 m, 1.5e-5 m/s, energy "
                  "9.1e-7 J over 10 s (10 singular passes); ~0.3 s. Every accuracy from 3e-8 "
                  "to 1e-5 passes the same way (1000-1003 steps, 2.4e-6 .. 1.4e-5 m); on an "
                  "AVX-512 machine (AMD EPYC) 1.2e-5 m, 8.2e-5 m/s, 4.0e-6 J at every "
                  "accuracy from 3e-8 to 1e-5: round-off amplified at the singular passes, "
                  "as natcoord's. Bounds ~2x the largest of these; "
                  "tighter, the step control meets the singular horizontal position: 2e-8, "
                  "1.2e-8, 8e-9 stall (no finish in 60 s; 1e-9 and 1e-10 in 120 s), 5e-9 and "
                  "constraint tolerances 1e-10/1e-9 at accuracy 1e-9/1e-10 finish on the "
                  "wrong branch (B0 2 m off, energy 14-36 J), 1e-8 happens to pass "
                  "(3.4e-7 m); PointOnLineConstraint (the two in-plane rows) instead stalls "
                  "the same at 1e-9 and 1e-10, CPodes fails at t = 0.71 s",
    },
    "drake": {
        "tolerance": "{ position = 4.5e-4, velocity = 9e-3, energy = 9e-2 }",
        "reason": "Drake 1.51.1: discrete MultibodyPlant, SAP, the 3 cranks on the ground "
                  "in the tree, loops B1c0 and B2c1 as AddBallConstraints between coupler "
                  "and crank; SAP's soft constraints make the error first order in dt, "
                  "largest after the singular passes: dt 1e-3: 6.9e-4 m, 8.1e-3 m/s, "
                  "energy 9.1e-2 J, loop gap 9.9e-8 m; dt 5e-4: 2.1e-4 m, 4.3e-3 m/s, "
                  "4.6e-2 J, gap 4.4e-8 m (~520 us per step); bounds ~2x at dt 5e-4",
    },
    "pybullet": {
        "tolerance": "{ position = 2.6e-4, velocity = 1.8e-3, energy = 1.4e-2 }",
        "reason": "PyBullet 3.2.7 multibody, loops B1c0 and B2c1 closed by point-to-point "
                  "constraints (erp 0.5), semi-implicit Euler: over 10 s (10 singular "
                  "passes) measured at dt 1e-3 3.3e-5 m, 5.8e-3 m/s, energy 9.1e-2 J; at "
                  "dt 1e-4 1.8e-4 m, 1.2e-3 m/s, 9.2e-3 J (~12 s); at dt 5e-5 3.8e-5 m, "
                  "3.6e-4 m/s, 4.6e-3 J: velocity and energy first order, the position "
                  "error a phase error that changes sign with dt; bounds ~1.5x",
    },
}, 40: {  # 20 s, 20 singular passes (t = 0.72, 1.24, 2.69, 3.21, 4.65, ... s)
    "natcoord": {
        "settings": '{ coordinates = "shared", method = "dop853", linsolve = "schur", '
                    'rtol = 5e-12, atol = 5e-14, project_tol = 1e-14, reference = { '
                    'method = "dop853", linsolve = "schur", rtol = 1e-12, atol = 1e-14, '
                    'project_tol = 1e-14 }, reference_check = { method = "dop853", '
                    'linsolve = "schur", rtol = 5e-12, atol = 5e-14, project_tol = 1e-14 } }',
        "tolerance": "{ position = 1e-8, velocity = 6e-8, energy = 1e-7 }",
        "reason": "the shared points of the natural coordinates (82 coordinates, 81 rod "
                  "rows), index-1 Schur path, dop853 rtol 5e-12, projection to 1e-14 m with "
                  "Phi summed in two doubles (points 40 m from the origin: the plain sum's "
                  "4e-13 m^2 round-off let the projections misplace the cranks by 1e-12 / "
                  "(distance to the singular position) and broke every step control at the "
                  "passes). Against the exact one-equation solution over 20 s (20 singular "
                  "passes): B0 2.6e-9 m, 1.7e-8 m/s, energy 2.6e-8 J; 1615 steps (769 "
                  "rejected, most at the passes), ~4 s. rtol 1e-11: 6.2e-9 m; 1e-12 (the "
                  "reference): 6.4e-10 m. Tolerances ~4x",
    },
    "mujoco": {
        "settings": "{ dt = 4e-4, solref_steps = 2.5 }",
        "tolerance": "{ position = 1e-3, velocity = 6e-3, energy = 2.5e-3 }",
        "reason": "RK4 dt 4e-4, 40 loops closed by connect equalities (solref 2.5 dt = 1 ms, "
                  "N = 2's time constant; solimp 0.9999): against the exact one-equation "
                  "solution 2.9e-4 m, 2.0e-3 m/s, energy 8.5e-4 J over 20 s, the same to two "
                  "digits as dt 1e-4 and 2e-4 with a 1 ms time constant (the soft loops set "
                  "the error, not RK4; dt 2e-4 at 10 dt = 2 ms: 7.4e-4 m, 2.1e-3 J); 50000 "
                  "steps, 16 s (11 s stepping) on a loaded machine, 54 s at dt 1e-4; ~3x",
    },
    "pinocchio": {
        "unsupported": "constraintDynamics (RK4 dt 1e-3, mu 1e-8) returns a non-finite "
                       "acceleration at t = 2.69 s, the third singular horizontal position "
                       "(the 40 loops lose rank 40), and by 2.6 s B0 is already 2.3e-3 m off "
                       "the exact solution; mu 1e-6 or 1e-4, dt 5e-4 and 100 proximal "
                       "iterations fail the same way between 2.67 and 3.18 s (mu 1e-4 "
                       "opens a loop by 5.5 cm)",
    },
    "exudyn": {
        "settings": '{ dt = 1e-3, linear_solver = "sparse", newton_atol = 1e-6 }',
        "tolerance": "{ position = 1e-3, velocity = 6e-3, energy = 4e-2 }",
        "reason": "generalized-alpha rho_inf 0.9, index 3, h 1e-3, EigenSparse (Exudyn's "
                  "dense default costs ~10 ms a step with 243 coordinates: ~200 s): measured "
                  "4.0e-4 m, 2.7e-3 m/s, energy 2.0e-2 J (drift -7.8e-5 J) over 20 s, "
                  "~40000 Newton iterations, ~10 s. Newton absolute tolerance 1e-6: tighter, "
                  "Newton stops at a singular position: rtol = atol = 1e-10 (N = 2's) at "
                  "t = 1.24 s (residual 4e-8), rtol 1e-8 or atol 1e-8 at 8.58 s (residual "
                  "3e-6); h 5e-4 stops at 0.72 s (atol 1e-10) or 8.58 s (atol 1e-6); "
                  "rho_inf 0.8 or modified Newton give the same errors. ~2x",
    },
    "dart": {
        "settings": '{ dt = 4e-4, erp = 1.0, loop_constraint = "ball" }',
        "tolerance": "{ position = 2.5e-5, velocity = 6e-3, energy = 1.5 }",
        "reason": "semi-implicit Euler dt 4e-4, ERP 1.0, 40 ball-joint loop constraints: "
                  "measured 1.0e-5 m, 2.3e-3 m/s, energy 0.62 J (first order, symplectic; "
                  "~620 J) over 20 s against the exact solution, 50000 steps, 73 s CPU (117 s "
                  "wall, loaded machine; DART's step, ~1.4 ms with 40 loop constraints, is "
                  "the whole cost). dt 2e-4: "
                  "2.6e-6 m, 1.2e-3 m/s, 0.31 J in ~160 s; dt 1e-4 (N = 2's) 6.5e-7 m, "
                  "5.7e-4 m/s, 0.16 J; dt 1e-3 6.1e-5 m, 5.6e-3 m/s, 1.5 J and still ~42 s. "
                  "~2.5x",
    },
    "simbody": {
        "settings": "{ accuracy = 1e-6 }",
        "tolerance": "{ position = 7e-5, velocity = 5e-4, energy = 5e-4 }",
        "reason": "Simbody 3.9 (OpenSim 4.6 wheel): PinJoints, 40 loops closed by "
                  "PointConstraint; RK-Merson at accuracy 1e-6 takes one step per 0.01 s "
                  "output interval (2000 steps) from natcoord's assembled start: measured "
                  "2.3e-5 m, 1.6e-4 m/s, energy 1.7e-4 J over 20 s against the exact "
                  "one-equation solution; ~15 s (+7 s readout). 1e-5 is identical; 1e-7 "
                  "2.5e-5 m (2003 steps); N = 2's 5e-8 and 3e-8, 1e-8 stall at the fifth "
                  "singular position (t = 4.65 s, no progress in 45 s), 1e-9 at the first "
                  "(0.72 s). Bounds ~3x",
    },
    "drake": {
        "unsupported": "tolerances not measured yet: the discrete SAP plant (81 bodies, 40 "
                  "ball constraints) costs 4.0 ms per step at dt 1e-3 (0.5 s measured: B0 "
                  "1.2e-6 m, loop gap 3.9e-9 m, before any singular pass), so the 20 s "
                  "run (~80 s) and its dt sweep are still to be done",
    },
    "pybullet": {
        "unsupported": "not within the run budget: 40 point-to-point loops on an 81-link "
                       "multibody cost 1.7-5 ms a step (the solver's rows, not its "
                       "iterations: 10 or 100 cost the same), so dt 1e-4 took 596 s for "
                       "the 20 s (2.8 ms a step) and ended 5.9e-2 m, 0.40 m/s, energy "
                       "0.38 J off the exact solution (20 singular passes); dt 1e-3 "
                       "(252 s) took the wrong branch at a pass, B0 1.87 m off",
    },
}}


def _f(x: float) -> str:
    """A coordinate as TOML: 3.0, -1.0."""
    return repr(float(x))


def n_four_bar(n: int, *, name: str | None = None, duration: float | None = None) -> str:
    """IFToMM A02 with N couplers, as case-file text.

    Parameters
    ----------
    n : int, >= 1: couplers (N + 1 cranks).
    name : the case name (must equal the file's stem); default ``a02_four_bar_n<N>``.
    duration : s; default the specification's: 20 s for N = 40, else 10 s.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n_four_bar: N must be an integer >= 1, got {n!r}")
    from ..model.casemodel import MAX_COORDINATES

    if 4 * (2 * n + 1) > MAX_COORDINATES:  # 2N + 1 rods of two points in the plane
        raise ValueError(f"n_four_bar: N = {n} makes {4 * (2 * n + 1)} natural coordinates, "
                         f"beyond natcoord's budget of {MAX_COORDINATES} (N <= "
                         f"{(MAX_COORDINATES // 4 - 1) // 2})")
    name = name or f"a02_four_bar_n{n}"
    option = "" if duration is None else f" --duration {duration:g}"  # as given
    duration = duration if duration is not None else (20.0 if n == 40 else 10.0)
    lines = [
        f"# Generated by `natcoord generate n_four_bar --n {n}{option} --out "
        f"cases/{name}.toml`:",
        "# edit natcoord/case/generate.py and regenerate rather than editing this file.",
        f'name = "{name}"',
        f'description = "IFToMM A02 N-four-bar, N = {n}: {n + 1} parallel cranks and {n} '
        f'couplers, uniform 1 m 1 kg rods, passing the singular horizontal position '
        f'(DOF 1 -> {n + 1}) ({duration:g} s); exact reduction to one '
        'equation in the crank angle"',
        "dimension = 2",
        "gravity = [0.0, -9.81]",
        f"duration = {_f(duration)}",
        f"output_dt = {_f(OUTPUT_DT)}",
        'tags = ["closed-loop", "2d", "singular", "iftomm", "analytic", "parametric"]',
        "",
        "# IFToMM multibody benchmark library, problem A02 (N-four-bar): N + 1 vertical cranks",
        "# of 1 m hinged to ground at x = 0, 1, ..., N, tips at y = 1, joined tip to tip by N",
        "# couplers of 1 m; every link a uniform rod of 1 kg; gravity -9.81 m/s^2 along y.",
        "# No [initial.pose]: every point is its world position at t = 0 (cranks vertical up).",
        "[ground]",
        "points = { " + ", ".join(f'O{i} = [{_f(i)}, 0.0]' for i in range(n + 1)) + " }",
        "",
    ]
    for i in range(n + 1):
        lines += ["[[bodies]]", f'name = "crank{i}"', 'kind = "uniform_rod"', "mass = 1.0",
                  f"points = {{ O{i} = [{_f(i)}, 0.0], B{i} = [{_f(i)}, 1.0] }}", ""]
    for i in range(n):
        lines += ["[[bodies]]", f'name = "coupler{i}"', 'kind = "uniform_rod"', "mass = 1.0",
                  f"points = {{ B{i} = [{_f(i)}, 1.0], B{i + 1} = [{_f(i + 1)}, 1.0] }}", ""]
    for i in range(n + 1):  # ground pivots
        lines += ["[[joints]]", f'name = "O{i}"', 'type = "revolute"',
                  f'bodies = ["ground", "crank{i}"]', f'points = ["O{i}", "O{i}"]', ""]
    for i in range(n):  # coupler i: left end on crank i, right end on crank i + 1
        lines += ["[[joints]]", f'name = "B{i}c{i}"', 'type = "revolute"',
                  f'bodies = ["crank{i}", "coupler{i}"]', f'points = ["B{i}", "B{i}"]', ""]
        lines += ["[[joints]]", f'name = "B{i + 1}c{i}"', 'type = "revolute"',
                  f'bodies = ["coupler{i}", "crank{i + 1}"]',
                  f'points = ["B{i + 1}", "B{i + 1}"]', ""]
    lines += [
        "[initial]",
        "# crank rate -1 rad/s: the tip B0 starts at (0, 1) m moving at (+1, 0) m/s",
        'velocity = { x_B0 = "1 m/s" }',
        "",
        "[channels]",
        'x_B0 = { kind = "position", body = "crank0", point = "B0", axis = "x" }',
        'y_B0 = { kind = "position", body = "crank0", point = "B0", axis = "y" }',
        'vx_B0 = { kind = "velocity", body = "crank0", point = "B0", axis = "x" }',
        'vy_B0 = { kind = "velocity", body = "crank0", point = "B0", axis = "y" }',
        'energy = { kind = "energy" }',
        "",
        "# The benchmark's own output and precision: what `natcoord bench --work-precision`",
        "# scores (error at these settings, least CPU time within the precision).",
        "[benchmark]",
        'channels = ["x_B0", "y_B0"]',
        'precision = "1e-3 m"',
        'source = "IFToMM A02 (N-four-bar): reference output the position of B0; precision '
        "the high level of the IFToMM Library of Computational Benchmark Problems (M. "
        "González et al., 'A collaborative benchmarking framework for multibody system "
        "dynamics', Engineering with Computers 26 (2010) 1-9): the library scores CPU time "
        'at two maximum allowed errors of the reference output, 1e-1 (low) and 1e-3 (high '
        'precision)"',
        "",
    ]
    measured = N_FOUR_BAR_MEASURED.get(n if duration == (20.0 if n == 40 else 10.0) else -1)
    if measured is None:
        lines += ["# natcoord: the linear-cost settings (joints, RK4 h 1 ms), within 1.4e-9 m of",
                  "# the exact reduction for N = 8 to 512; the other engines' settings as",
                  f"# measured for N = 2 and 40. Tolerances for N = {n} are not measured: run",
                  "# the case and add tolerance blocks with their reasons.",
                  ""]
    for engine, spec in N_FOUR_BAR_ENGINES.items():
        block = (measured or {}).get(engine, {})
        lines.append(f"[engines.{engine}]")
        if "unsupported" in block:
            lines += [f'unsupported = "{block["unsupported"]}"', ""]
            continue
        lines.append(f"settings = {block.get('settings', spec['settings'])}")
        if "tolerance" in block:
            lines += [f"tolerance = {block['tolerance']}", f'reason = "{block["reason"]}"']
        lines.append("")
    return "\n".join(lines).rstrip("\n") + "\n"


FAMILIES: dict[str, Callable[..., str]] = {"n_four_bar": n_four_bar}


def case_file_path(out: str) -> Path:
    """The case file that ``--out`` of ``generate`` and ``import`` names, as typed: NatcoordError
    unless it ends in ``.toml`` with a case name as its stem (a trailing separator, a folder
    that need not exist, used to become a file of the folder's name, and a file without
    .toml one that no command finds)."""
    from .casefile import MAX_NAME, NAME_PATTERN

    if not out or out.endswith(("/", os.sep)):
        raise NatcoordError(f"--out {out!r}: names a folder; give the case file to write, "
                            "FOLDER/NAME.toml")
    path = Path(out)
    if path.suffix != ".toml":
        raise NatcoordError(f"--out {out!r}: a case file ends in .toml (run finds cases "
                            "by it)")
    if not NAME_PATTERN.fullmatch(path.stem):
        raise NatcoordError(f"--out {out!r}: its stem is the case name: use at most "
                            f"{MAX_NAME} letters, digits and _ . + - (not starting with . + "
                            "or -)")
    return path


def check_duration(duration: float, output_dt: float = OUTPUT_DT) -> None:
    """NatcoordError naming ``--duration`` when a case of that length, sampled every
    ``output_dt`` s, would not load (the loader's rules on duration and output_dt)."""
    from .casefile import MAX_SAMPLES

    k = duration / output_dt
    if k > MAX_SAMPLES:
        raise NatcoordError(f"--duration {duration:g}: {k:.3g} output samples (every "
                            f"{output_dt:g} s) are beyond the budget of {MAX_SAMPLES}")
    if round(k) < 1 or abs(k - round(k)) > 1e-9:
        raise NatcoordError(f"--duration {duration:g}: must be a multiple of the output "
                            f"step {output_dt:g} s")


def write_case(path: Path, text: str, *, force: bool = False, assemble: bool = False) -> None:
    """Write a generated case file to ``path`` once it loads back and, with ``assemble``,
    assembles at t = 0 as a run would (NatcoordError otherwise, naming ``path``, not the
    trial copy). An existing file is kept (NatcoordError) unless ``force``; a folder or a
    special file in its place is never replaced."""
    from ..suite.io import check_user_file, write_user_file
    from .casefile import load_case

    path = Path(path)
    check_user_file(path, force=force)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:  # the stem, the case name: bytes of another encoding
        raise NatcoordError(f"{path}: the file name is not valid UTF-8; its stem is the "
                            "case name: use at most 64 letters, digits and _ . + -") from None
    with tempfile.TemporaryDirectory(prefix="natcoord-generate-") as tmp:
        trial = Path(tmp) / path.name
        trial.write_text(text, encoding="utf-8")
        try:
            case = load_case(trial)
        except CaseError as e:
            raise NatcoordError("generated file does not load: "
                                f"{CaseError(str(path), e.field, e.reason)}") from None
        if assemble:
            from ..outputs.channels import initial_body_states
            try:
                initial_body_states(case)
            except NatcoordError as e:
                why = (CaseError(str(path), e.field, e.reason) if isinstance(e, CaseError)
                       else f"{path}: {str(e).replace(str(trial), str(path))}")
                raise NatcoordError(f"generated file does not run (it does not assemble at "
                                    f"t = 0): {why}") from None
    write_user_file(path, text, force=force)
