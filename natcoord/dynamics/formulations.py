"""The formulations, by name: each is one module of :mod:`natcoord.dynamics` that holds its
options (a :class:`~natcoord.dynamics.options.Formulation`), its Python loop (a
:class:`~natcoord.dynamics.common.FormulationLoop`, the options' ``loop``) and the entry to
its compiled loop. Adding a formulation is one module and its line here.

``index1``  Lagrange equations with the acceleration constraints (:mod:`.index1`).
``maggi``   Maggi / R-method by coordinate partitioning (:mod:`.maggi`).
``index3``  Augmented Lagrangian index-3 with the trapezoidal rule (:mod:`.index3`).

Multipliers are computed once per output sample by
:func:`~natcoord.dynamics.common.multipliers` (minimum norm), so every formulation reports
the same lambda.
"""

from __future__ import annotations

from .index1 import Index1
from .index3 import Index3
from .maggi import Maggi
from .options import Formulation

FORMULATIONS: dict[str, type[Formulation]] = {f.name: f for f in (Index1, Maggi, Index3)}
DEFAULT_METHOD = {name: f.default_method for name, f in FORMULATIONS.items()}
