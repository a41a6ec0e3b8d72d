"""natcoord: a natural-coordinate multibody solver and a cross-engine validation suite."""

__version__ = "0.1.0"

from .case.casefile import load_case, load_cases  # noqa: E402
from .case.mechanism import Case  # noqa: E402
from .errors import AssemblyError, CaseError, ExistenceError, NatcoordError, Unsupported  # noqa: E402
from .outputs.result import Motion, Result, Status, evaluate_channels  # noqa: E402

__all__ = ["__version__", "load_case", "load_cases", "Case", "Motion", "Result", "Status",
           "evaluate_channels", "NatcoordError", "CaseError", "AssemblyError",
           "ExistenceError", "Unsupported",
           "Builder", "Model", "State", "integrate", "accelerations", "project", "Solution",
           "Solver", "Index1", "Maggi", "Index3", "Adaptive", "Fixed", "reactions"]

# the solver (build a model, integrate it, read its reactions), imported when first used:
# numba and the compiled loops stay out of the bench's processes that do not integrate
_SOLVER = {"Builder": "model.builder", "Model": "model.model", "State": "model.kinematics",
           "integrate": "dynamics.forward", "accelerations": "dynamics.forward",
           "project": "dynamics.forward", "Solution": "dynamics.forward",
           "Solver": "dynamics.solver", "Index1": "dynamics.solver", "Maggi": "dynamics.solver",
           "Index3": "dynamics.solver", "Adaptive": "dynamics.solver", "Fixed": "dynamics.solver"}


def __getattr__(name: str):
    import importlib
    if name == "reactions":
        return importlib.import_module(".outputs.reactions", __name__)
    if name in _SOLVER:
        return getattr(importlib.import_module(f".{_SOLVER[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
