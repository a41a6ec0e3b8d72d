"""``natcoord check-engine``: a fixed battery of conformance checks on any engine.

Every run goes through the engine's worker process (:func:`natcoord.suite.runner.
run_subprocess`), as in a suite, and is short (a case's first :data:`SPAN_S` s, the
pendulum's :data:`SWING_S` s):

* **reaction sign** and **reaction, joint reversed**: a uniform rod (2 kg, 1 m) hanging at
  rest from a pin; the pin's reaction on the second body named is m g up (+19.62 N), and
  with the joint's bodies listed the other way round it is the force on the ground, -m g;
* **energy**: the same rod released horizontal at rest (conservative): the drift of its
  energy over 1 s on the energy scale (m g L), at the engine's default settings;
* **momentum**: the rod spinning about its pin without gravity (2 rad/s): its angular
  momentum about the pin is conserved, so theta = 2 t exactly (error on 2 rad), and the
  pin's reaction is the centripetal force m w^2 L / 2 = 4 N (when reactions are declared);
* **convergence order**: when the engine declares a step setting (``dt`` or ``h``), the rod's
  angle error against natcoord at rtol 1e-12 at steps 0.01 s and 0.005 s: log2 of their
  ratio (info when both are at round-off);
* **reference <case>**: every case of the project the engine can run (its capabilities, the
  case file), over its first :data:`SPAN_S` s at the case's settings, judged against the
  stored reference with the gate's error computation
  (:func:`natcoord.suite.compare.channel_errors`) and the case file's tolerances;
* **determined reactions <case>**: on a case with redundant constraints (undetermined
  channels in its reference), the determined reactions judged and the undetermined ones
  counted as shown, not judged.

Each row: check, result (pass, fail, info: measured but nothing to judge it by, skipped:
the engine cannot run it, with the reason), the figure, the capability it touches.
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..case.casefile import load_case
from ..case.mechanism import FORCE_KINDS, Case
from .compare import channel_errors
from .evidence import BadEvidence, BadReference, cell_folder, read_reference, read_table
from .runner import prepare, run_subprocess

SPAN_S = 0.5  # simulated seconds of a reference case at most
SWING_S = 1.0  # the pendulum of the energy and order checks
RUN_TIMEOUT_S = 300.0
G = 9.81
ROD = """name = "check_rod"
description = "a uniform rod (2 kg, 1 m) on a pin: check-engine's conformance case"
dimension = 2
gravity = [0.0, {gravity}]
duration = {duration}
output_dt = 0.01
[ground]
points = {{ O = [0.0, 0.0] }}
[[bodies]]
name = "rod"
kind = "uniform_rod"
mass = 2.0
points = {{ O = [0.0, 0.0], P = [1.0, 0.0] }}
[[joints]]
name = "O"
type = "revolute"
bodies = {bodies}
points = ["O", "O"]
[initial]
fix = {{ theta = "{angle} deg" }}
velocity = {{ theta = {rate} }}
[initial.pose]
rod = {{ origin = [0.0, 0.0], angle = "{angle} deg" }}
[channels]
theta = {{ kind = "angle", body = "rod" }}
O_x = {{ kind = "reaction", joint = "O", axis = "x" }}
O_y = {{ kind = "reaction", joint = "O", axis = "y" }}
energy = {{ kind = "energy" }}
"""
REACTION_RTOL = 1e-3  # of m g: a sign or frame error is 100 %, an engine's own error far less
ENERGY_RTOL = 1e-3  # of m g L over 1 s: a damping default or a dissipative step shows
MOMENTUM_RTOL = 1e-3  # of w T: damping or a dissipative step shows
PULL_RTOL = 1e-2  # of m w^2 L / 2: a missing centripetal term is 100 %, a first-order
# engine's own error at its default step 1e-4..1e-3 (PyBullet at dt 1e-4: 1.4e-3 at worst)
MIN_ORDER = 0.8  # an error that does not fall at least about linearly with the step


@dataclass
class Row:
    check: str
    result: str  # pass | fail | info | skipped
    figure: str
    capability: str
    detail: str = ""


def rod(folder: Path, *, reversed_joint: bool = False, angle: float = -90.0,
        duration: float = 0.1, rate: float = 0.0, gravity: float = -G) -> Case:
    """The conformance rod as a loaded case (written to ``folder``): ``rate`` rad/s at
    t = 0, ``gravity`` m/s^2 along y."""
    bodies = '["rod", "ground"]' if reversed_joint else '["ground", "rod"]'
    path = (folder / f"{'rev' if reversed_joint else 'fwd'}{angle:g}w{rate:g}g{gravity:g}"
            / "check_rod.toml")
    path.parent.mkdir(exist_ok=True)
    path.write_text(ROD.format(bodies=bodies, angle=angle, duration=duration, rate=rate,
                               gravity=gravity), encoding="utf-8")
    return load_case(path)


def features(case: Case) -> str:
    """What of a case an engine must model: the capabilities its rows touch."""
    from ..engines.tree import spanning_tree

    out = [f"{case.dimension}-D", *sorted({j.type for j in case.joints})]
    if spanning_tree(case)[1] or case.rods:
        out.append("loops")
    out += [x for x, present in (("drivers", case.drivers), ("springs", case.springs),
                                 ("rods", case.rods), ("forces", case.forces)) if present]
    if any(c.kind in FORCE_KINDS for c in case.channels):
        out.append("reactions")
    return ", ".join(out)


class Battery:
    """The checks on one engine; runs go to a temporary results folder."""

    def __init__(self, engine: str, cases_dir: Path, references: Path,
                 say: Callable[[str], None] = lambda s: None):
        self.engine, self.cases_dir, self.references, self.say = (engine, Path(cases_dir),
                                                                   Path(references), say)
        self.tmp = Path(tempfile.mkdtemp(prefix="natcoord-check-"))
        self.rows: list[Row] = []

    def run(self, case: Case, engine: str | None = None, settings: dict | None = None):
        """(record, table or None) of one run in the engine's process."""
        engine = engine or self.engine
        self.say(f"{case.name} in {engine}")
        rec = run_subprocess(prepare(case), engine, self.tmp, RUN_TIMEOUT_S, settings)
        if rec["status"] != "ok":
            return rec, None
        path = cell_folder(self.tmp, case.name) / f"{engine}.csv"
        try:
            return rec, read_table(path.read_bytes(), path, case)
        except (OSError, BadEvidence) as e:  # this run's results, not the command's input
            why = str(e).replace(f"{path}: ", "")
            return {**rec, "status": "failed", "reason": f"its results cannot be read: "
                    f"{why}"}, None

    def add(self, *args, **kw) -> None:
        self.rows.append(Row(*args, **kw))

    def not_run(self, check: str, rec: dict, capability: str) -> None:
        result = "skipped" if rec["status"] in ("unsupported", "skipped") else "fail"
        self.add(check, result, rec["status"], capability, rec.get("reason", "")[:300])

    # ------------------------------------------------------------------- the checks
    def reactions(self) -> None:
        from ..engines import adapter

        cap = "reactions: force on the second body named, world axes"
        for rev, want in ((False, 2 * G), (True, -2 * G)):
            check = "reaction, joint reversed" if rev else "reaction sign"
            if not adapter(self.engine).CAPABILITIES.reactions:
                self.add(check, "skipped", "no reactions declared", cap)
                continue
            rec, t = self.run(rod(self.tmp, reversed_joint=rev))
            if t is None:
                self.not_run(check, rec, cap)
                continue
            y, x = t["O_y"].to_numpy(), t["O_x"].to_numpy()
            err = float(np.max(np.abs(np.r_[y - want, x])))
            ok = err <= REACTION_RTOL * 2 * G
            self.add(check, "pass" if ok else "fail",
                     f"O_y {np.median(y):+.6g} N (want {want:+.4g}), max error {err:.2g} N",
                     cap, "" if ok else "the pin's reaction must be the force it applies "
                     "to the joint's second body, in world axes (+y up)")

    def momentum(self) -> None:
        from ..engines import adapter

        w, T = 2.0, SWING_S
        rec, t = self.run(rod(self.tmp, angle=0.0, duration=T, rate=w, gravity=0.0))
        cap = "integration: angular momentum about a pin, no gravity"
        if t is None:
            self.not_run("momentum", rec, cap)
            return
        err = float(np.max(np.abs(np.unwrap(t["theta"].to_numpy()) - w * t["t"].to_numpy())))
        ok = err <= MOMENTUM_RTOL * w * T
        figure = f"angle off w t by {err:.2g} rad over {T:g} s"
        if adapter(self.engine).CAPABILITIES.reactions:
            pull = np.hypot(t["O_x"].to_numpy(), t["O_y"].to_numpy())
            want = 2.0 * w**2 * 0.5  # m w^2 (L / 2)
            rerr = float(np.max(np.abs(pull - want)))
            ok = ok and rerr <= PULL_RTOL * want
            figure += f"; pin pull {np.median(pull):.6g} N (want {want:g}), error {rerr:.2g} N"
        self.add("momentum", "pass" if ok else "fail", figure, cap,
                 "" if ok else "a spinning rod must keep its angular momentum (no damping, no "
                 "dissipative step) and its pin must pull it inward by m w^2 L / 2")

    def energy_and_order(self) -> None:
        swing = rod(self.tmp, angle=0.0, duration=SWING_S)
        rec, t = self.run(swing)
        cap = "integration: a conservative pendulum at the default settings"
        if t is None:
            self.not_run("energy", rec, cap)
        else:
            e = t["energy"].to_numpy()
            drift = float(np.max(np.abs(e - e[0])) / (2 * G * 1.0))
            ok = drift <= ENERGY_RTOL
            self.add("energy", "pass" if ok else "fail",
                     f"drift {drift:.2g} of m g L over {SWING_S:g} s", cap,
                     "" if ok else "energy leaks: look for default damping, a dissipative "
                     "integrator or a step too large for the defaults")
        from ..engines import adapter

        mod = adapter(self.engine)
        name = mod.CAPABILITIES.step or next(
            (s.name for s in mod.SETTINGS if s.name in ("dt", "h")), "")
        if not name:
            self.add("convergence order", "info", "no step setting (dt or h) declared",
                     "settings")
            return
        with_ = dict(mod.CAPABILITIES.step_with)
        ref_rec, ref = self.run(swing, "natcoord", {"rtol": 1e-12, "atol": 1e-12})
        if ref is None:
            self.not_run("convergence order", ref_rec, "natcoord reference")
            return
        h0 = swing.output_dt  # 0.01 s and 0.005 s: errors well above round-off
        errors = []
        for h in (h0, h0 / 2):
            rec, t = self.run(swing, settings={**with_, name: h})
            if t is None:
                self.not_run("convergence order", rec, f"settings: {name}")
                return
            errors.append(float(np.max(np.abs(t["theta"] - ref["theta"]))))
        cap = f"settings: {name}"
        if min(errors) < 1e-11:
            self.add("convergence order", "info", f"errors {errors[0]:.2g}, {errors[1]:.2g} "
                     f"rad at {name} {h0:g}, {h0 / 2:g} s: at round-off, no order", cap)
            return
        order = math.log2(errors[0] / errors[1]) if errors[1] > 0 else float("inf")
        ok = order >= MIN_ORDER
        self.add("convergence order", "pass" if ok else "fail",
                 f"{order:.2f} ({errors[0]:.2g} -> {errors[1]:.2g} rad, {name} "
                 f"{h0:g} -> {h0 / 2:g} s)", cap,
                 "" if ok else f"the error does not fall with {name}: is the step "
                 "setting passed to the integrator?")

    def references_(self) -> None:
        from .worker import cannot_run

        for f in sorted(self.cases_dir.glob("*.toml")):
            case = load_case(f)
            check = f"reference {case.name}"
            why = cannot_run(case, self.engine)
            if why:
                self.add(check, "skipped", "unsupported", features(case), why[:300])
                continue
            n = int(round(case.duration / case.output_dt))
            k = max(1, min(n, int(round(SPAN_S / case.output_dt))))
            short = replace(case, duration=k * case.output_dt)
            try:
                reference, undetermined = read_reference(case, self.references)
            except BadReference as e:
                self.add(check, "info", "no reference", features(case), str(e)[:300])
                continue
            rec, t = self.run(short)
            if t is None:
                self.not_run(check, rec, features(case))
                continue
            channels, verdict, reason = channel_errors(short, self.engine, t,
                                                       reference.iloc[:k + 1], undetermined)
            worst = max(channels.items(), key=lambda kv: -1.0 if kv[1]["max_rel"] is None
                        else kv[1]["max_rel"])
            figure = (f"{worst[0]} {worst[1]['max_abs']:.2g} {worst[1]['unit']} "
                      f"({short.duration:g} s)" if worst[1]["max_abs"] is not None else "")
            result = {"pass": "pass", "fail": "fail"}.get(verdict, "info")
            bad = [n for n, c in channels.items() if c["pass"] is False]
            self.add(check, result, figure, features(case),
                     reason + (f": {', '.join(bad)}" if bad else ""))
            if undetermined:
                self.determined(case, channels, undetermined)

    def determined(self, case: Case, channels: dict, undetermined) -> None:
        forces = {n: c for n, c in channels.items() if c["kind"] in FORCE_KINDS}
        det = {n: c for n, c in forces.items() if n not in undetermined}
        judged = [c for c in det.values() if c["pass"] is not None]
        failed = [n for n, c in det.items() if c["pass"] is False]
        result = "fail" if failed else "pass" if judged else "info"
        self.add(f"determined reactions {case.name}", result,
                 f"{len(judged) - len(failed)} of {len(judged)} determined within tolerance; "
                 f"{len([n for n in forces if n in undetermined])} undetermined shown, not "
                 "judged", "reactions with redundant constraints",
                 ", ".join(failed))


def check_engine(engine: str, cases_dir: Path, references: Path,
                 say: Callable[[str], None] = lambda s: None) -> dict:
    """Run the battery on ``engine``: ``{engine, version, seconds, rows}`` (rows as dicts)."""
    import shutil

    from ..engines.registry import version_of

    t0 = time.perf_counter()
    b = Battery(engine, cases_dir, references, say)
    try:
        b.reactions()
        b.momentum()
        b.energy_and_order()
        b.references_()
    finally:
        shutil.rmtree(b.tmp, ignore_errors=True)
    version, why, _ = version_of(engine)  # in a child process: the adapter's code
    version = version or f"unknown (version() {why})"
    return {"engine": engine, "version": version,
            "seconds": round(time.perf_counter() - t0, 1),
            "rows": [asdict(r) for r in b.rows]}
