"""Engine adapters, chosen by name (:mod:`natcoord.engines.registry`: the built-ins and
every plug-in registered in the ``natcoord.engines`` entry-point group)."""

from __future__ import annotations

from .registry import adapter, discover, engine_names

__all__ = ["adapter", "discover", "engine_names"]
