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

Formulations (the equations of motion, :mod:`natcoord.formulations`):

``Index1``  Lagrange equations with the acceleration constraints; drift ``stabilization``
            by projection (default), Baumgarte or none; ``linsolve`` auto | schur | qr.
``Maggi``   null-space / R-method by coordinate partitioning; re-partitioned when the
            dependent block degrades by ``repartition_growth``.
``Index3``  augmented Lagrangian index-3 with mass-orthogonal projections; ``penalty``
            alpha h^2/4 relative to max|M|.

Integrators (:mod:`natcoord.integrators`): ``dop853`` (adaptive), ``dopri5`` (adaptive or
fixed), ``rk4`` (fixed), ``trapezoidal`` (fixed; index3 only) and scipy's ``DOP853``,
``RK45``, ``Radau``, ``LSODA``, ``BDF`` (adaptive).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import ClassVar

SCIPY_METHODS = ("DOP853", "RK45", "Radau", "LSODA", "BDF")
ODE_METHODS = ("rk4", "dopri5", "dop853", *SCIPY_METHODS)
METHODS = (*ODE_METHODS, "trapezoidal")
FIXED_ONLY = ("rk4", "trapezoidal")
ADAPTIVE_ONLY = ("dop853", *SCIPY_METHODS)


def _positive(owner: str, name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or \
            not math.isfinite(value) or value <= 0:
        raise ValueError(f"{owner}: {name} must be a positive number, got {value!r}")


def _choice(owner: str, name: str, value, choices: tuple) -> None:
    if value not in choices:
        raise ValueError(f"{owner}: {name} {value!r} is not one of {', '.join(choices)}")


def _flag(owner: str, name: str, value) -> None:
    if not isinstance(value, bool):
        raise ValueError(f"{owner}: {name} must be true or false, got {value!r}")


@dataclass(frozen=True)
class Adaptive:
    """Error-controlled steps: relative and absolute tolerance on every component of
    [q, qd] (m, m/s)."""

    rtol: float = 1e-10
    atol: float = 1e-12

    def __post_init__(self):
        _positive("Adaptive", "rtol", self.rtol)
        _positive("Adaptive", "atol", self.atol)


@dataclass(frozen=True)
class Fixed:
    """Fixed steps of ``h`` seconds (shortened to land on every output sample)."""

    h: float

    def __post_init__(self):
        _positive("Fixed", "h", self.h)


@dataclass(frozen=True)
class Formulation:
    """Options every formulation shares: Newton and projection tolerances (on |Phi|, m),
    the relative rank tolerance of Phi_q, and ``compiled``: run the whole integration as one
    numba loop when the model allows (else, or False, the Python loop)."""

    name: ClassVar[str] = ""
    methods: ClassVar[tuple[str, ...]] = ODE_METHODS
    project_tol: float = 1e-13
    newton_tol: float = 1e-13
    rank_tol: float = 1e-9
    compiled: bool = True

    def __post_init__(self):
        for f in ("project_tol", "newton_tol", "rank_tol"):
            _positive(type(self).__name__, f, getattr(self, f))
        _flag(type(self).__name__, "compiled", self.compiled)

    def options(self) -> dict:
        """The options as a plain dict (what :mod:`natcoord.formulations` reads)."""
        return asdict(self)


@dataclass(frozen=True)
class Index1(Formulation):
    """Index-1 Lagrange equations. ``baumgarte`` (alpha, beta) 1/s; compiled with
    projection and dop853, dopri5 or rk4; ``generated``: on its Schur path, with kernels
    written out for the model (:mod:`natcoord.codegen`) when it allows, else the generic
    sparse kernels."""

    name: ClassVar[str] = "index1"
    stabilization: str = "projection"
    baumgarte: tuple[float, float] = (10.0, 10.0)
    linsolve: str = "auto"
    generated: bool = True

    def __post_init__(self):
        super().__post_init__()
        _choice("Index1", "stabilization", self.stabilization, ("projection", "baumgarte",
                                                                 "none"))
        _choice("Index1", "linsolve", self.linsolve, ("auto", "schur", "qr"))
        if len(self.baumgarte) != 2:
            raise ValueError(f"Index1: baumgarte must be (alpha, beta), got {self.baumgarte!r}")
        for x in self.baumgarte:
            _positive("Index1", "baumgarte", x)
        _flag("Index1", "generated", self.generated)
        object.__setattr__(self, "baumgarte", tuple(float(x) for x in self.baumgarte))


@dataclass(frozen=True)
class Maggi(Formulation):
    """Maggi's null-space equations; re-partition when max|R^d| grows by this factor."""

    name: ClassVar[str] = "maggi"
    repartition_growth: float = 1.5

    def __post_init__(self):
        super().__post_init__()
        _positive("Maggi", "repartition_growth", self.repartition_growth)


@dataclass(frozen=True)
class Index3(Formulation):
    """Index-3 augmented Lagrangian; ``penalty`` alpha h^2/4 relative to max|M| (1e6 and
    above leave a round-off floor in lambda; Newton failures retry with it x100)."""

    name: ClassVar[str] = "index3"
    methods: ClassVar[tuple[str, ...]] = ("trapezoidal",)
    penalty: float = 1e4

    def __post_init__(self):
        super().__post_init__()
        _positive("Index3", "penalty", self.penalty)


FORMULATIONS: dict[str, type[Formulation]] = {f.name: f for f in (Index1, Maggi, Index3)}
DEFAULT_METHOD = {"index1": "dop853", "maggi": "dop853", "index3": "trapezoidal"}


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
        method = s.pop("method", DEFAULT_METHOD[name])
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
