"""Engine adapters, chosen by name."""

from __future__ import annotations

import importlib
from types import ModuleType

from ..mechanism import ENGINES

_MODULES = {"natcoord": "natcoord_engine", "mujoco": "mujoco_engine",
            "pinocchio": "pinocchio_engine", "exudyn": "exudyn_engine", "dart": "dart_engine",
            "simbody": "simbody_engine", "pybullet": "pybullet_engine"}


def adapter(name: str) -> ModuleType:
    """The adapter module of engine ``name`` (importing it does not import the engine)."""
    if name not in _MODULES:
        raise KeyError(f"unknown engine {name!r}; engines are {', '.join(ENGINES)}")
    return importlib.import_module(f"{__name__}.{_MODULES[name]}")
