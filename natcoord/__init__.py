"""natcoord: a natural-coordinate multibody solver and a cross-engine validation suite."""

__version__ = "0.1.0"

from .casefile import load_case, load_cases  # noqa: E402
from .errors import AssemblyError, CaseError, ExistenceError, NatcoordError, Unsupported  # noqa: E402
from .mechanism import Case  # noqa: E402
from .result import Motion, Result, Status, evaluate_channels  # noqa: E402

__all__ = ["__version__", "load_case", "load_cases", "Case", "Motion", "Result", "Status",
           "evaluate_channels", "NatcoordError", "CaseError", "AssemblyError",
           "ExistenceError", "Unsupported"]
