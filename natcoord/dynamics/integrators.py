"""Integrators by name (``INTEGRATORS``) and the one time loop that drives a formulation.

``rk4``          classical Runge-Kutta, fixed step (order 4)
``dopri5``       Dormand-Prince 5(4): adaptive (rtol, atol) or fixed step (order 5); the
                 formulation's ``post_step`` (projection, re-partitioning) runs after every
                 accepted step, so k1 is re-evaluated at the corrected state (no FSAL)
``dop853``       Dormand-Prince 8(5,3), adaptive; on index1 and maggi the whole run is one
                 compiled kernel (:mod:`natcoord.compiled.index1`, :mod:`natcoord.compiled.maggi`)
                 when the model allows, else the Python loop below runs it.
``trapezoidal``  the index-3 formulation's own implicit step (order 2), fixed step
scipy names      (``DOP853``, ``RK45``, ``Radau``, ``LSODA``, ``BDF``): ``solve_ivp`` between
                 output samples, ``post_step`` at each sample only

Adaptive steps cross the output samples (in this loop as in the compiled one): a sample
inside a step comes from the method's continuous extension (dopri5: order 4, dop853: order
7), projected like a step end on index1 (Maggi rebuilds its dependent coordinates). Fixed
steps are shortened to land on every sample instead.
"""

from __future__ import annotations

import math

import numpy as np

from ..compiled import stepcontrol as sc
from ..errors import StepFailure
from ..model.kinematics import singular_hint
from .options import SCIPY_METHODS


class ExplicitRK:
    """Explicit Runge-Kutta method from its Butcher tableau (class constants)."""

    name = ""
    order = 0
    C: np.ndarray
    A: np.ndarray
    B: np.ndarray
    E: np.ndarray | None = None  # B - B_embedded: error estimate weights

    @classmethod
    def step(cls, f, t, y, h):
        """One step: (y_new, error estimate or None)."""
        y_new, err, _ = cls.stages(f, t, y, h)
        return y_new, err

    @classmethod
    def stages(cls, f, t, y, h):
        """One step: (y_new, error estimate or None, stages K (s, N))."""
        s = len(cls.B)
        K = np.empty((s, len(y)))
        for i in range(s):
            K[i] = f(t + cls.C[i] * h, y + h * (cls.A[i, :i] @ K[:i]))
        y_new = y + h * (cls.B @ K)
        err = h * (cls.E @ K) if cls.E is not None else None
        return y_new, err, K

    @classmethod
    def dense(cls, f, t, y, y_new, h, K):
        """Continuous extension on the step: a function x in [0, 1] -> y(t + x h)."""
        return None


class RK4(ExplicitRK):
    name, order = "rk4", 4
    C, A, B = sc.RK4_C, sc.RK4_A, sc.RK4_B


class DormandPrince5(ExplicitRK):
    name, order = "dopri5", 5
    C, A, B, E = sc.DOPRI5_C, sc.DOPRI5_A, sc.DOPRI5_B, sc.DOPRI5_E

    @classmethod
    def dense(cls, f, t, y, y_new, h, K):
        """Hairer's order-4 continuous extension (stage 7 = f at y_new)."""
        def at(x):
            out = np.empty_like(y)
            sc.dense_dopri5(K, sc.DOPRI5_P, y, h, x, out)
            return out
        return at


class DormandPrince853(ExplicitRK):
    """DOP853; the 13th stage is f(t + h, y_new) for the error."""

    name, order = "dop853", 7  # order of the error estimate, for the step control
    C, A, B = sc.DOP853_C[:13], sc.DOP853_A[:13, :13], sc.DOP853_B

    @classmethod
    def stages(cls, f, t, y, h):
        """One step: (y_new, (h E5 K, h E3 K), K (13, N)) for Hairer's error norm."""
        A, B, C = cls.A, cls.B, cls.C
        K = np.empty((13, len(y)))
        for i in range(13):
            K[i] = f(t + C[i] * h, y + h * (A[i, :i] @ K[:i]))
        return y + h * (B @ K), (h * (sc.DOP853_E5 @ K), h * (sc.DOP853_E3 @ K)), K

    @classmethod
    def dense(cls, f, t, y, y_new, h, K):
        """Order-7 continuous extension: three more stages (Hairer's CONTD8)."""
        A, C = sc.DOP853_A, sc.DOP853_C
        K = np.vstack([K, np.empty((3, len(y)))])
        for s in range(13, 16):
            K[s] = f(t + C[s] * h, y + h * (A[s, :s] @ K[:s]))
        Fd = np.empty((3 + len(sc.DOP853_D), len(y)))
        sc.dense_dop853(y, y_new, h, K, 13, sc.DOP853_D, Fd)

        def at(x):
            out = np.empty_like(y)
            sc.dense_at(Fd, y, x, out)
            return out
        return at


INTEGRATORS = {"rk4": RK4, "dopri5": DormandPrince5, "dop853": DormandPrince853,
               "trapezoidal": None,
               **{k: None for k in SCIPY_METHODS}}


def _rms(x):
    return math.sqrt(float(np.mean(x * x))) if len(x) else 0.0



def substeps(span: float, h: float) -> int:
    """Fixed steps over an output interval of ``span`` s with steps of at most ``h`` s:
    equal steps that land on every sample (the compiled loops take the same number)."""
    return max(1, math.ceil(span / h - 1e-9))

def time_loop(form, y, times, *, method: str, h: float | None, rtol: float, atol: float,
              record) -> None:
    """Advance ``y`` through ``times`` (T,), calling ``record(k, t, y)`` at every sample.

    Fixed step when ``h`` is given (steps of at most h that land on each sample), adaptive
    otherwise (dopri5, dop853 and the scipy methods).
    """
    cnt = form.cnt
    if method not in INTEGRATORS:
        raise ValueError(f"unknown integrator {method!r}; expected one of {', '.join(INTEGRATORS)}")
    if method not in form.methods:
        raise ValueError(f"formulation {form.name!r} does not run with {method!r}; "
                         f"use one of {', '.join(form.methods)}")
    if method == "dop853" and h is not None:
        raise ValueError("dop853 is adaptive only: give rtol/atol, not h")
    if method in ("rk4", "trapezoidal") and h is None:
        raise ValueError(f"{method} is a fixed-step method: give h")
    record(0, times[0], y)
    if len(y) == 0:  # no degrees of freedom left: kinematics at every sample
        for k in range(1, len(times)):
            record(k, times[k], y)
        return
    if h is None and method not in SCIPY_METHODS:
        _adaptive(form, INTEGRATORS[method], y, times, rtol, atol, record)
        return
    h_adapt = None
    for k in range(1, len(times)):
        t0, t1 = float(times[k - 1]), float(times[k])
        if method in SCIPY_METHODS:
            from scipy.integrate import solve_ivp  # imported when used: start-up time
            sol = solve_ivp(form.rhs, (t0, t1), y, method=method, rtol=rtol, atol=atol,
                            first_step=None if h_adapt is None else min(h_adapt, t1 - t0),
                            **({} if h is None else {"max_step": h}))
            if not sol.success:
                raise RuntimeError(f"integration failed at t = {t0:.6g} s: {sol.message}")
            cnt.steps += len(sol.t) - 1
            h_adapt = float(sol.t[-1] - sol.t[-2]) if len(sol.t) > 1 else None
            y = form.post_step(t1, sol.y[:, -1])
        else:
            nsub = substeps(t1 - t0, h)
            hh = (t1 - t0) / nsub
            for i in range(nsub):
                t = t0 + i * hh
                y = form.step(t, y, hh) if method == "trapezoidal" else \
                    DormandPrince5.step(form.rhs, t, y, hh)[0] if method == "dopri5" else \
                    RK4.step(form.rhs, t, y, hh)[0]
                y = form.post_step(t + hh, y)
                cnt.steps += 1
        record(k, t1, y)


def _sample_projection(form):
    """How an interpolated sample is corrected: index1 projects it like a step end (its
    ``post_step``); Maggi's state already rebuilds the dependent coordinates, and its
    ``post_step`` may re-partition, which a sample must not do."""
    return form.post_step if form.name == "index1" else (lambda t, y: y)


def _adaptive(form, rk, y, times, rtol, atol, record):
    """Embedded-pair step control over ``times``; steps cross the samples, which come from
    the method's continuous extension."""
    cnt, f = form.cnt, form.rhs
    at_sample = _sample_projection(form)
    t, t_end, k = float(times[0]), float(times[-1]), 1
    f0 = f(t, y)  # Hairer's first guess from |y| and |f|
    scale = atol + rtol * np.abs(y)
    h = sc.initial_step(_rms(y / scale), _rms(f0 / scale), t_end - t)
    expo = sc.EXPONENT[rk.name]
    while k < len(times):
        hh = min(h, t_end - t)
        try:
            y_new, err, K = rk.stages(f, t, y, hh)
        except StepFailure:
            if sc.underflow(hh * 1e-4, t):
                raise
            cnt.rejected += 1
            h = sc.STAGE_FAILURE_FACTOR * hh
            continue
        scale = atol + rtol * np.maximum(np.abs(y), np.abs(y_new))
        if isinstance(err, tuple):  # DOP853: Hairer's combination of the 5th and 3rd order
            e = sc.dop853_norm(float(np.sum((err[0] / scale) ** 2)),
                               float(np.sum((err[1] / scale) ** 2)), len(y), 1.0)
        else:
            e = sc.rms_norm(float(np.sum((err / scale) ** 2)), len(y))
        if not math.isfinite(e):
            raise RuntimeError(f"non-finite state at t = {t:.6g} s")
        if e > 1.0:
            cnt.rejected += 1
            h = hh * sc.reject_factor(e, expo)
            if sc.underflow(h, t):
                raise RuntimeError(_underflow_message(form, t, y))
            continue
        t1 = t_end if hh == t_end - t else t + hh
        tol_t = sc.SAMPLE_TOL * max(1.0, abs(t1))
        inner = None
        while k < len(times) and times[k] < t1 - tol_t:  # samples inside the step
            inner = inner or rk.dense(f, t, y, y_new, hh, K)
            record(k, float(times[k]), at_sample(float(times[k]), inner((times[k] - t) / hh)))
            k += 1
        t, y = t1, form.post_step(t1, y_new)
        cnt.steps += 1
        if k < len(times) and times[k] <= t1 + tol_t:
            record(k, float(times[k]), y)
            k += 1
        h = hh * sc.accept_factor(e, expo)


def _underflow_message(form, t, y) -> str:
    """Step size underflow, with the nearness of a singular position when that is why."""
    msg = f"step size underflow at t = {t:.6g} s"
    try:
        q, _ = form.state(t, y)
        J = form.cs.jacobian(q, t)
    except Exception:  # the message must not hide the failure
        return msg
    return msg + singular_hint(J, form.opt.get("rank_tol", 1e-9))
