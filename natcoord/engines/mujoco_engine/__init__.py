"""MuJoCo as an engine: a kinematic tree of hinge, slide and ball joints plus soft equalities.

One model for every case: a 2-D case is lifted into 3-D (:mod:`natcoord.engines.planar`),
built by one MJCF builder (:mod:`.mjcf`), stepped and sampled (:mod:`.stepping`) with its
forces read in 3-D (:mod:`.forces`), and dropped back to a planar Motion at the end (again
:mod:`natcoord.engines.planar`). Every body is placed
at its frame at t = 0 (``init[body]``), so MuJoCo starts at natcoord's assembled state
(checked to 1e-9).

Modelling choices (each one that applies is repeated in ``EngineRun.notes``):

* Tree: :func:`natcoord.engines.tree.spanning_tree`. MuJoCo has no point-on-line equality, so
  when that tree would cut a joint that is not a point joint (prismatic, cylindrical,
  universal), the tree is rebuilt with those joints taken first (the loop is then cut at a
  revolute or spherical joint instead); a loop that can only be closed at such a joint is
  unsupported.
* Tree joints: revolute -> hinge about the case's axis (2-D: z); spherical -> ball;
  prismatic -> slide; cylindrical -> slide and hinge on the same axis; universal -> two
  hinges in the child body, which MuJoCo composes as parent x Rot(axis, q1) x Rot(axis2, q2):
  the first axis stays on the first body, the second on the second (a Cardan joint, exact;
  no intermediate body needed).
* Loop-closing revolute or spherical joints: ``connect`` equalities between two sites
  (``site1`` on the joint's first body, ``site2`` on its second; 3 rows: a loop revolute's
  axis alignment is left to the tree, so the redundancy differs from natcoord's while the
  motion does not). They are soft: RK4, Newton, tolerance 1e-10, solimp 0.9999 and solref
  time constant ``solref_steps`` x dt keep the loop closed to ~1e-9 m.
* Massless rods: a spatial tendon between two sites, its length held by a tendon equality
  (one row, soft like every MuJoCo equality, with the same solref/solimp). Measured against a
  light body with two connects on five_bar: angle error 3.7e-5 rad against 3.1e-3 rad for a
  1e-3 kg light rod, whose loops open past 0.1 mm when it is made lighter.
* Spring-dampers: the same tendon with ``stiffness``, ``damping`` and ``springlength`` = the
  spring's rest length (MuJoCo's passive tendon spring: ``-k (l - l0) - c dl/dt``).
* Particles: a point mass. On a revolute, spherical or universal tree joint it is welded to
  its parent (its rotation carries no energy, so no joint is needed: exact); on a slide or
  floating it cannot turn and is given ``particle_inertia`` (kg m^2), as MuJoCo wants a
  positive one. Its frame is reported with natcoord's convention (angle 0, identity
  rotation), the origin following its point.
* Inertia: a point mass (zero inertia) gets 1e-10 m r^2 (r: its farthest point); a tensor
  with a zero principal moment (a slender uniform rod about its own axis) gets
  ``zero_inertia`` x its largest principal moment along that axis.
* Bodies not reached from the ground: in a 2-D case they stay in the plane (slide x, slide
  y, hinge z), in 3-D a free joint; a particle only translates.
* Loads: constant torques and forces at the centre of mass through ``xfrc_applied`` (exact);
  a force at another point is unsupported.
* Drivers (prescribed motions): unsupported, with the measured substitute in
  :data:`DRIVERS_UNSUPPORTED`.

Reactions (force the joint applies to its second body, world axes) and tensions: see
:mod:`.forces`; both are evaluated at the stored state (``mj_forward`` then
``mj_rnePostConstraint``), not read from the step that produced the state.
"""

from __future__ import annotations

from ...case.mechanism import Case
from ...errors import Unsupported
from ..base import EngineRun, merged, steps_per_sample
from ..capabilities import Capabilities
from ..schema import C_INT_MAX, Setting, defaults, particle_inertia

NAME = "mujoco"
PACKAGE = "mujoco"
SETTINGS = (
    Setting("dt", "number", 1e-4, "time step; must divide the case's output interval",
            "s", exclusive_minimum=0.0),
    Setting("integrator", "choice", "RK4", "MuJoCo's integrator (<option integrator>)",
            choices=("Euler", "RK4", "implicit", "implicitfast")),
    Setting("solver", "choice", "Newton", "MuJoCo's constraint solver (<option solver>)",
            choices=("PGS", "CG", "Newton")),
    Setting("tolerance", "number", 1e-10, "the constraint solver's tolerance (0: run "
            "every iteration)", minimum=0.0),
    Setting("iterations", "integer", 100, "the constraint solver's iteration cap",
            minimum=1, maximum=C_INT_MAX),
    Setting("ls_iterations", "integer", 50, "the solver's line-search iteration cap",
            minimum=1, maximum=C_INT_MAX),
    Setting("solref_steps", "number", 10.0, "time constant of the soft equalities (loops, "
            "rods) in time steps; below 2 MuJoCo's refsafe would clamp it", minimum=2.0),
    Setting("solref_damping", "number", 1.0, "damping ratio of the soft equalities",
            exclusive_minimum=0.0),
    Setting("solimp", "numbers", (0.9999, 0.9999, 0.001, 0.5, 2.0), "impedance of the soft "
            "equalities: dmin, dmax (below 1), width (m), midpoint (below 1), power (>= 1)",
            exclusive_minimum=0.0, length=5),
    particle_inertia(False, "on a slide or floating: MuJoCo needs one; it does not act"),
    Setting("max_loop_drift", "number", 1e-4, "a soft loop or rod opened wider than this is "
            "a failed run", "m", exclusive_minimum=0.0),
    Setting("loop_axis_offset", "number", 0.0, "> 0 holds a loop-closing 3-D revolute's axis "
            "by a second connect this far along it (0: one connect, a ball joint)", "m",
            minimum=0.0),
    Setting("zero_inertia", "number", 1e-6, "inertia added along a zero principal axis "
            "(a slender rod's own), times the largest principal moment",
            exclusive_minimum=0.0),
)
DEFAULTS = defaults(SETTINGS)


def check_settings(settings: dict) -> list[tuple[str, str]]:
    """solimp's bounds that differ between its entries (MuJoCo would clamp them)."""
    imp = settings.get("solimp")
    if imp is None:
        return []
    out = [(f"solimp[{k}]", f"must be below 1, got {imp[k]!r}") for k in (0, 1, 3)
           if imp[k] >= 1.0]
    if imp[4] < 1.0:
        out.append(("solimp[4]", f"must be >= 1 (a power), got {imp[4]!r}"))
    return out


JOINT_TYPES = ("revolute", "prismatic", "spherical", "universal", "cylindrical")  # modelled
DRIVERS_UNSUPPORTED = (
    "prescribed motions (drivers): MuJoCo has no rheonomic constraint (its equalities have no "
    "time argument). The closest substitute, a joint equality to a heavy 'clock' slide moving "
    "at 1 m/s, was measured on driven_rod against its closed form: angle 9.8e-6 rad, torque "
    "1.0e-3 N with a 1e6 kg clock (the clock lags as it feeds the driver torque); a 1e10 kg "
    "clock holds the angle to 1.5e-9 rad but ill-conditions the solver (torque 0.57 N off), "
    "and a body point's coordinate cannot be a joint equality at all")

BODY_LOADS_UNSUPPORTED = ("MuJoCo's xfrc_applied is in world axes and held over a step, so "
                          "a load given in a body's frame would lag the body's rotation "
                          "inside the RK4 stages")
CAPABILITIES = Capabilities(
    output_steps=True,  # dt must divide the output interval (base.steps_per_sample)
    loops="soft",  # connect equalities: solref/solimp let a loop open by a small gap
    loop_joints={"revolute", "spherical"},  # a connect holds a point only
    recut={"prismatic", "cylindrical", "universal"},  # mjcf.split_tree
    drivers=(), forces="com",
    why={"drivers": DRIVERS_UNSUPPORTED.split(": ", 1)[1],
         "body_loads": BODY_LOADS_UNSUPPORTED,
         "loop_joints": "MuJoCo has no point-on-line equality (a connect equality holds a "
                        "point only)",
         "forces": "MuJoCo's xfrc_applied acts at the centre of mass and is held over a "
                   "step, so the moment of a force elsewhere would lag the body's rotation"})


def version() -> str:
    import mujoco

    return mujoco.__version__


def _refuse(case: Case) -> None:
    """What MuJoCo cannot model, before anything is built."""
    if case.drivers:
        raise Unsupported(DRIVERS_UNSUPPORTED)
    for j in case.joints:
        if j.type not in JOINT_TYPES:
            raise Unsupported(f"joint {j.name}: type {j.type!r}")
    for b in case.bodies:
        if b.mass <= 0:
            raise Unsupported(f"body {b.name} is massless; MuJoCo bodies need mass")


def run(case: Case, init, settings: dict) -> EngineRun:
    """Simulate ``case`` from ``init`` at the case's sample times (see the module).
    MuJoCo's warnings are kept from its own handler, which writes MUJOCO_LOG.TXT into the
    current folder: the run fails on them through the warning counters it checks."""
    import mujoco

    from ...case.mjcf import caught_warnings

    with caught_warnings(mujoco):
        return _run(mujoco, case, init, settings)


def _run(mujoco, case: Case, init, settings: dict) -> EngineRun:
    from ..planar import check_start, drop, lift_case, lift_init
    from . import mjcf, stepping

    s = merged(DEFAULTS, settings)
    dt = float(s["dt"])
    k = steps_per_sample(case, dt)
    if float(s["solref_steps"]) < 2.0:
        raise ValueError("solref_steps below 2 is clamped by MuJoCo's refsafe; use >= 2")
    _refuse(case)
    space = lift_case(case)
    mjcf.split_tree(space)  # an unsupported loop is refused before the state is read
    frames = lift_init(case, init)
    planar = case.dimension == 2
    built, m, d, build = stepping.load_model(
        mujoco, space, lambda: mjcf.build(space, frames, s, planar))

    sampler = stepping.Sampler(mujoco, m, d, space, built)
    sampler.sample(0)
    stepping.check_state(mujoco, d, 0.0)
    check_start(space, frames, sampler.out, "MuJoCo")
    times = case.times

    def at_sample(i):
        stepping.check_state(mujoco, d, times[i])
        sampler.sample(i)
        stepping.check_state(mujoco, d, times[i])
        if sampler.drift > float(s["max_loop_drift"]):
            raise RuntimeError(f"a loop opened or a rod stretched by {sampler.drift:.3g} m by "
                               f"t = {times[i]:.6g} s (max_loop_drift {s['max_loop_drift']} "
                               "m): the soft constraints do not hold at these settings")

    wall, n_steps = stepping.step_samples(mujoco, m, d, len(times), k, at_sample)
    counters = {"steps": n_steps, "nv": int(m.nv), "loop_drift_m": sampler.drift,
                "max_solver_iterations": sampler.max_iter}
    notes = built.notes + [f"integrator {s['integrator']}, solver {s['solver']}, tolerance "
                           f"{s['tolerance']}, contacts disabled, dt {dt} s"]
    out = sampler.out
    motion = drop(case, times, out.origin, out.rotation, out.velocity, out.omega, out.forces,
                  rod_force=out.rod_force, acceleration=out.acceleration, alpha=out.alpha)
    return EngineRun(motion, build, wall, n_steps, s, counters, notes)
