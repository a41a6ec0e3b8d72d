"""How natcoord integrates, as small frozen objects: formulation, integrator, step control.

    Solver()                                              # index1, dop853, rtol 1e-10
    Solver(Index1(stabilization="baumgarte"), "rk4", Fixed(1e-3))
    Solver(Index3(penalty=1e6), "trapezoidal", Fixed(5e-4))
    Solver(Maggi(), "dop853", Adaptive(rtol=1e-9, atol=1e-11))

Every combination is checked when the object is made, so an invalid one (rk4 without a
step, dop853 with one, index3 with anything but its trapezoidal rule) cannot reach the
time loop. :meth:`Solver.from_settings` reads the flat ``[engines.natcoord].settings`` of a
case file (``formulation``, ``method``, ``rtol``, ``atol``, ``h`` and the formulation
options), so a case file that asks for an invalid combination is refused when it is loaded.

Formulations (the equations of motion, :mod:`natcoord.dynamics.formulations`):

``Index1``  Lagrange equations with the acceleration constraints; drift ``stabilization``
            by projection (default), Baumgarte or none; ``linsolve`` auto | schur | qr.
``Maggi``   null-space / R-method by coordinate partitioning; re-partitioned when the
            dependent block degrades by ``repartition_growth``.
``Index3``  augmented Lagrangian index-3 with mass-orthogonal projections; ``penalty``
            alpha h^2/4 relative to max|M|.

Integrators (:mod:`natcoord.dynamics.integrators`): ``dop853`` (adaptive), ``dopri5`` (adaptive or
fixed), ``rk4`` (fixed), ``trapezoidal`` (fixed; index3 only) and scipy's ``DOP853``,
``RK45``, ``Radau``, ``LSODA``, ``BDF`` (adaptive).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from .formulations import DEFAULT_METHOD, FORMULATIONS
from .index1 import Index1
from .index3 import Index3
from .maggi import Maggi
from .options import (
    ADAPTIVE_ONLY,
    FIXED_ONLY,
    METHODS,
    Adaptive,
    Fixed,
    Formulation,
    _choice,
)

__all__ = ["Solver", "Adaptive", "Fixed", "Formulation", "Index1", "Maggi", "Index3",
           "FORMULATIONS", "DEFAULT_METHOD", "case_solver"]


@dataclass(frozen=True)
class Solver:
    """A formulation, an integrator (by name) and a step control that fit together."""

    formulation: Formulation = field(default_factory=Index1)
    method: str = "dop853"
    step: Adaptive | Fixed = field(default_factory=Adaptive)

    def __post_init__(self):
        f, m = self.formulation, self.method
        if not isinstance(f, Formulation):
            raise ValueError(f"formulation must be Index1(), Maggi() or Index3(), got {f!r}")
        _choice("Solver", "method", m, METHODS)
        if m not in f.methods:
            raise ValueError(f"formulation {f.name!r} does not run with {m!r}; use "
                             f"{' or '.join(f.methods)}")
        if m in FIXED_ONLY and not isinstance(self.step, Fixed):
            raise ValueError(f"{m} is a fixed-step method: give a step h (Fixed(h))")
        if m in ADAPTIVE_ONLY and not isinstance(self.step, Adaptive):
            raise ValueError(f"{m} is adaptive: give rtol/atol (Adaptive), not a step h")
        if not isinstance(self.step, (Adaptive, Fixed)):
            raise ValueError(f"step must be Adaptive(rtol, atol) or Fixed(h), got {self.step!r}")

    @property
    def h(self) -> float | None:
        """The fixed step (s), or None for adaptive steps."""
        return self.step.h if isinstance(self.step, Fixed) else None

    def describe(self) -> str:
        """'index1 dop853 rtol 1e-10' or 'index3 trapezoidal h 0.001 s'."""
        s = self.step
        return f"{self.formulation.name} {self.method} " + (
            f"h {s.h:g} s" if isinstance(s, Fixed) else f"rtol {s.rtol:g}")

    def settings(self) -> dict:
        """The flat settings that :meth:`from_settings` reads back."""
        s = self.step
        return {"formulation": self.formulation.name, "method": self.method,
                **({"h": s.h} if isinstance(s, Fixed) else {"rtol": s.rtol, "atol": s.atol}),
                **self.formulation.options()}

    @classmethod
    def from_settings(cls, settings: dict) -> Solver:
        """A Solver from flat settings: ``formulation``, ``method`` (default: dop853, or
        trapezoidal for index3), ``h`` (a fixed step, s) or ``rtol``/``atol``, and the
        formulation's options. Raises ValueError naming the key and the problem."""
        s = dict(settings)
        name = s.pop("formulation", "index1")
        _choice("settings", "formulation", name, tuple(FORMULATIONS))
        form_cls = FORMULATIONS[name]
        method = s.pop("method", form_cls.default_method)
        h = s.pop("h", None)
        tol = {k: s.pop(k) for k in ("rtol", "atol") if k in s}
        known = {f.name for f in fields(form_cls)}
        unknown = sorted(set(s) - known)
        if unknown:
            others = sorted(set().union(*({f.name for f in fields(c)} for c in
                                          FORMULATIONS.values())) - known)
            why = (f"not an option of {name}" if unknown[0] in others else "unknown key")
            raise ValueError(f"settings: {unknown[0]!r}: {why}; keys are formulation, "
                             f"method, h, rtol, atol, {', '.join(sorted(known))}")
        if h is not None and tol:
            raise ValueError(f"settings: give a fixed step h or tolerances "
                             f"{'/'.join(tol)}, not both")
        step = Fixed(h) if h is not None else Adaptive(**tol)
        return cls(form_cls(**s), method, step)


DEFAULT_TOLERANCES = {"rtol": 1e-12, "atol": 1e-14}  # natcoord's own, as an engine
MODEL_KEYS = ("coordinates",)  # case settings that choose the model, not the solver
REFERENCE_KEYS = ("reference", "reference_check")  # solver settings of the stored reference


def case_solver(settings: dict) -> Solver:
    """The Solver that a case's ``[engines.natcoord].settings`` ask for: adaptive steps at
    rtol 1e-12, atol 1e-14 unless they say otherwise (model and reference keys aside).
    Raises ValueError naming the key and the problem."""
    own = {k: v for k, v in settings.items() if k not in MODEL_KEYS + REFERENCE_KEYS}
    if own.get("h") is None:
        own = DEFAULT_TOLERANCES | {k: v for k, v in own.items() if k != "h"}
    return Solver.from_settings(own)
