"""Errors a user can act on: each names where the problem is and what it is."""

from __future__ import annotations

import os
from pathlib import Path


class NatcoordError(Exception):
    """Base class of every error natcoord raises on purpose."""


class CaseError(NatcoordError):
    """A case file is malformed: names the file, the field and the reason.

    The command line prints ``str(error)`` and exits with status 2.
    """

    def __init__(self, file: str, field: str, reason: str):
        self.file, self.field, self.reason = str(file), field, reason
        super().__init__(f"{self.file}: {field}: {reason}" if field else f"{self.file}: {reason}")


class ModelError(NatcoordError):
    """A loaded case describes a mechanism that cannot be modelled: names the field of the
    case (``bodies[1] (plate).points``, ``joints``) and the reason; the loader adds the
    file (a :class:`CaseError`)."""

    def __init__(self, field: str, reason: str):
        self.field, self.reason = field, reason
        super().__init__(f"{field}: {reason}")


class AssemblyError(NatcoordError):
    """The constraints cannot be met from the given initial guess."""


class ExistenceError(NatcoordError):
    """ker M ∩ ker Phi_q ≠ {0}: a motion allowed by the constraints carries no kinetic energy
    (García de Jalón & Gutiérrez-López, Eq. (37)), so accelerations are not determined."""


class Unsupported(NatcoordError):
    """An engine cannot model part of a case; the message says which part and why."""


class StepFailure(NatcoordError, RuntimeError):
    """A stage of a step cannot be evaluated (e.g. a position Newton diverged because the
    step reached too far); the adaptive loop rejects the step and retries a shorter one."""


class StoredFileError(NatcoordError, ValueError):
    """A stored file (history, baseline, reference, summary, bench) is missing a part,
    malformed or unreadable: names the file and the problem. Exit status 2."""


class EnvironmentFault(NatcoordError):
    """The machine, not the input: a full disk, a read-only folder, an unwritable file
    outside the results. Exit status 5."""


def unwritable(folder: Path) -> tuple[Path, bool] | None:
    """Whether files can be written in ``folder`` (made if need be), looking only: None
    when they can, else (the nearest part of it that exists, whether that part is a file
    rather than a folder this process may write)."""
    for part in (Path(folder), *Path(folder).parents):
        if part.exists() or part.is_symlink():
            if not part.is_dir():
                return part, True
            return None if os.access(part, os.W_OK | os.X_OK) else (part, False)
    return None
