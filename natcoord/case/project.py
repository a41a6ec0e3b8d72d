"""Where a natcoord project keeps its cases, references and reports, found from anywhere.

The command line works from any directory. The project folder (the one holding ``cases/``
and ``references/``) is, in this order:

1. ``$NATCOORD_HOME`` when it is set (a folder holding ``cases/``; anything else is
   refused, never replaced by another project);
2. the current directory or the nearest parent that holds ``cases/``;
3. the checkout this natcoord was installed from (an editable install of the repository).

Options (``--cases-dir``, ``--references``, ``--out``) override each folder on its own.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import NatcoordError

ENV = "NATCOORD_HOME"


class ProjectNotFound(NatcoordError):
    """No project folder: the message lists where it looked."""


def candidates() -> list[tuple[str, Path]]:
    """(how, folder) in the order they are tried."""
    out = []
    if os.environ.get(ENV):
        out.append((f"${ENV}", Path(os.environ[ENV]).expanduser()))
    here = Path.cwd().resolve()
    out += [("the current directory or a parent", p) for p in (here, *here.parents)]
    out.append(("the installed checkout", Path(__file__).resolve().parents[2]))
    return out


def home() -> Path:
    """The project folder (see the module docstring); raises ProjectNotFound."""
    given = os.environ.get(ENV)
    if given:
        folder = Path(given).expanduser()
        if not folder.is_dir():
            raise ProjectNotFound(f"${ENV}={given}: no such folder; set it to a natcoord "
                                  "project (a folder holding cases/) or unset it")
        if not (folder / "cases").is_dir():
            raise ProjectNotFound(f"${ENV}={given}: not a natcoord project (no cases/ "
                                  "folder); set it to one or unset it")
        return folder
    tried = []
    for how, folder in candidates():
        if (folder / "cases").is_dir():
            return folder
        if how != "the current directory or a parent" or folder == Path.cwd().resolve():
            tried.append(f"{folder} ({how})")
    raise ProjectNotFound("no natcoord project found (a folder with cases/): looked in "
                          + ", ".join(tried) + f" and the parents of the current directory; "
                          f"set {ENV} or give --cases-dir")


def resolve(given: Path | None, default: str) -> Path:
    """``given`` as it is, else ``default`` under the project folder."""
    return Path(given) if given is not None else home() / default
