"""Test shorthand: a case's natural-coordinate model and its state at t = 0."""

from __future__ import annotations

import numpy as np

from natcoord.case.mechanism import Case
from natcoord.model import casemodel
from natcoord.model.kinematics import State
from natcoord.model.model import Model
from natcoord.outputs import channels as outputs

_BUILT: dict[int, casemodel.CaseModel] = {}


def build_model(case: Case, coordinates: str = "joints") -> Model:
    """The model of a case (:func:`natcoord.model.casemodel.build`)."""
    cm = casemodel.build(case, coordinates)
    _BUILT[id(cm.model)] = cm
    return cm.model


def initial_state(model: Model) -> State:
    """The case's state at t = 0 for a model made by :func:`build_model`."""
    return casemodel.initial_state(_BUILT[id(model)])


def coordinate(model: Model, body: str, point: str, axis: str = "x") -> int:
    """Index in q of a world coordinate of a body's point (an element of the model)."""
    return int(model.elements[f"{body}.{point}"].cols["xyz".index(axis)])


def replace(model: Model, **fields) -> Model:
    """``dataclasses.replace`` of a built model that :func:`initial_state` still knows."""
    import dataclasses

    cm = _BUILT[id(model)]
    new = dataclasses.replace(model, **fields)
    _BUILT[id(new)] = dataclasses.replace(cm, model=new)
    return new


def body_columns(model: Model, body: str) -> np.ndarray:
    """Indices in q of a body's basis elements (its own coordinates)."""
    cm = _BUILT[id(model)]
    return np.concatenate([model.elements[e].cols for e in cm.basis[body]])


def body_angle(model: Model, body: str, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
    """(T,) unwrapped angle of a 2-D body's frame along q, qd (T, n), rad."""
    return outputs.frames(_BUILT[id(model)], q, qd).angle(body)
