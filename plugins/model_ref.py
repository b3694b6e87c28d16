"""Passing models to Mitsuba plugins, whose properties cannot hold Python objects.

`model_ref(model)` registers a model and returns a string for the `csg` shape's `model`
property; `resolve` turns such a string (or the text of a native JSON model) back into it.
"""
from __future__ import annotations

import itertools

from mitsuba_csg.engine.optimize import OptimizedModel
from mitsuba_csg.errors import CSGError
from mitsuba_csg.formats import native_json
from mitsuba_csg.model.nodes import Node

_PREFIX = "mitsuba-csg:model:"
_registry: dict[str, object] = {}
_counter = itertools.count()


def model_ref(model) -> str:
    """A string naming `model` for `{'type': 'csg', 'model': ...}` (the model stays alive)."""
    if not isinstance(model, (Node, OptimizedModel)):
        raise CSGError(f"model_ref: expected a CSG model, got {type(model).__name__}")
    key = f"{_PREFIX}{next(_counter)}"
    _registry[key] = model
    return key


def resolve(text: str):
    if text.startswith(_PREFIX):
        if text not in _registry:
            raise CSGError(f"csg shape: {text!r} names no model registered in this process (use csg.model_ref)")
        return _registry[text]
    if text.lstrip().startswith("{"):
        return native_json.loads(text, source="<model property>")
    raise CSGError("csg shape: 'model' must come from csg.model_ref(model) or be native JSON text")
