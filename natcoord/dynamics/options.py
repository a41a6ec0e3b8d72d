"""The options a formulation and a step control take, as small frozen objects that check
themselves when made: :class:`Adaptive`, :class:`Fixed` and :class:`Formulation`, the base
of each formulation's options (:mod:`natcoord.dynamics.index1`, ``maggi``, ``index3``)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
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
    default_method: ClassVar[str] = "dop853"
    loop: ClassVar[type]  # its Python loop (a FormulationLoop), set by its module
    project_tol: float = 1e-13
    newton_tol: float = 1e-13
    rank_tol: float = 1e-9
    compiled: bool = True

    def __post_init__(self):
        for f in ("project_tol", "newton_tol", "rank_tol"):
            _positive(type(self).__name__, f, getattr(self, f))
        _flag(type(self).__name__, "compiled", self.compiled)

    def options(self) -> dict:
        """The options as a plain dict (what the formulation's loop reads)."""
        return asdict(self)
