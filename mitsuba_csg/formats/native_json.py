"""The native model format: one CSG tree and its materials as a JSON document (`.json`).

    {"format": "mitsuba-csg", "version": 1,
     "materials": {"rind": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.6, 0.2]}}},
     "root": {"type": "difference", "material": "rind", "children": [
         {"type": "box", "size": [2.0, 2.0, 2.0]},
         {"type": "sphere", "radius": 0.3, "transform": [{"translate": [1.0, 0.0, 0.0]}]}]}}

`docs/formats/native-json.md` is the reference. Files are untrusted input: every problem is
a `FormatError` (a `ModelError`) whose message starts with the file (or "<dict>") and the
JSON path of the bad value, e.g. `model.json: root.children[3].radius: must be > 0, got -1`.
Deep trees neither crash nor recurse: the tree is read and written with explicit stacks, and
files nested too deeply for Python's `json` module are parsed by an iterative parser here.

Saving writes each node's local matrix (full float precision) and keeps the node structure,
so `from_dict(to_dict(m))` has leaves with identical parameters, world matrices and materials.
"""
from __future__ import annotations

import copy
import json
import math
import re
from json.decoder import scanstring

import numpy as np

from .. import memory
from ..errors import ModelError
from ..model import transform as tf
from ..model import values
from ..model.nodes import OPERATIONS, PRIMITIVE_TYPES, Node, Operation, Primitive
from ..model.polyhedra import MAX_PLANES
from .reading import FormatError, read_model_bytes

FORMAT = "mitsuba-csg"
VERSION = 1                      # the version `save` writes
SUPPORTED_VERSIONS = (1,)        # the versions `load` reads
MAX_DEPTH = 10_000               # operation levels above a leaf (the root is at depth 0)
MAX_NODES = 10_000_000           # nodes in one document, operations and primitives together
MAX_FILE_BYTES = 2 ** 30         # a larger file is refused before it is read
MAX_MATERIAL_DEPTH = 64          # nesting of one material's BSDF dict


# ---- Paths and messages ----
# A JSON path is a linked tuple (parent, key or index) built per node at no cost; it is turned
# into text only for an error message. `None` is the document itself ("$").

_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_PATH_HEAD, _PATH_TAIL = 8, 8     # long paths keep this many segments at each end


def _path_text(path) -> str:
    segments = []
    while path is not None:
        path, key = path
        segments.append(key)
    if not segments:
        return "$"
    segments.reverse()
    hidden = 0
    if len(segments) > 1 + 2 * (_PATH_HEAD + _PATH_TAIL):
        # Node levels are two segments ("children", i): keep whole levels at both ends.
        head, tail = 1 + 2 * _PATH_HEAD, len(segments) - 2 * _PATH_TAIL
        if isinstance(segments[tail], int):
            tail -= 1
        hidden = tail - head
        segments = segments[:head] + [None] + segments[tail:]
    parts = []
    for i, key in enumerate(segments):
        if key is None:
            parts.append(f"<{hidden} more path segments>")
        elif isinstance(key, int):
            parts.append(f"[{key}]")
        elif _IDENTIFIER.match(key) and len(key) <= 60:
            parts.append(key if i == 0 else "." + key)
        else:
            parts.append(f"[{json.dumps(key)}]" if len(key) <= 60 else f"[{json.dumps(key[:57])}...]")
    return "".join(parts)


def _fail(source: str, path, message: str):
    raise FormatError(f"{source}: {_path_text(path)}: {message}")


class _NonFinite:
    """What the JSON literals NaN, Infinity and -Infinity parse to, so that checks can name them."""

    __slots__ = ("literal",)

    def __init__(self, literal: str):
        self.literal = literal

    def __repr__(self) -> str:
        return self.literal


class _DuplicateKeys(dict):
    """A JSON object that repeated a key (json keeps the last one silently; we refuse it)."""

    __slots__ = ("duplicates",)


def _object_pairs(pairs):
    obj = dict(pairs)
    if len(obj) != len(pairs):
        seen, dups = set(), []
        for k, _ in pairs:
            if k in seen and k not in dups:
                dups.append(k)
            seen.add(k)
        obj = _DuplicateKeys(pairs)
        obj.duplicates = dups
    return obj


def _describe(value) -> str:
    """A value as a message shows it: JSON spelling for scalars, a kind for containers."""
    if isinstance(value, _NonFinite):
        return value.literal
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, (int, np.integer)):
        text = str(int(value)) if abs(int(value)) < 10 ** 30 else "a huge integer"
        return text
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return "NaN" if math.isnan(v) else ("Infinity" if v == math.inf else
                                             "-Infinity" if v == -math.inf else repr(v))
    if isinstance(value, str):
        text = json.dumps(value)
        return "the string " + (text if len(text) <= 40 else text[:37] + '..."')
    if isinstance(value, (list, tuple)):
        return f"a list of {len(value)} item{'s' if len(value) != 1 else ''}"
    if isinstance(value, dict):
        return "an object"
    return f"a {type(value).__name__}"


def _key(value) -> str:
    return _quoted(value) if isinstance(value, str) else _describe(value)


def _keys_text(keys) -> str:
    keys = list(keys)
    more = f" and {len(keys) - 8} more" if len(keys) > 8 else ""
    return ", ".join(_quoted(k) for k in keys[:8]) + more


def _names_text(names) -> str:
    """Names the file defines, unquoted, each cut to 60 characters, at most 8 of them."""
    names = list(names)
    more = f" and {len(names) - 8} more" if len(names) > 8 else ""
    return ", ".join(n if len(n) <= 60 else n[:57] + "..." for n in names[:8]) + more


def _quoted(text: str, limit: int = 60) -> str:
    """A name from the file for a message: quoted, cut to `limit` characters (a file may hold
    a megabyte-long key)."""
    return repr(text) if len(text) <= limit else repr(text[:limit - 3]) + f"... ({len(text)} characters)"


# ---- Value checks (each returns the checked value or raises FormatError) ----

def _object(value, source, path, what: str) -> dict:
    if not isinstance(value, dict):
        _fail(source, path, f"expected {what} (a JSON object), got {_describe(value)}")
    if isinstance(value, _DuplicateKeys):
        _fail(source, path, f"duplicate key(s) {_keys_text(value.duplicates)}")
    return value


def _list(value, source, path, what: str) -> list:
    if not isinstance(value, (list, tuple)):
        _fail(source, path, f"expected {what}, got {_describe(value)}")
    return value


def _checked(check, value, source, path, *args):
    """A shared value check (`model.values`), its problem reported at the JSON path."""
    if isinstance(value, _NonFinite):
        _fail(source, path, f"must be finite, got {value.literal}")
    try:
        return check(value, *args, describe=_describe)
    except values.ValueProblem as e:
        _fail(source, path, str(e))


def _number(value, source, path) -> float:
    if type(value) is float and math.isfinite(value):      # the common case, first
        return value
    return _checked(values.number, value, source, path)


def _positive(value, source, path) -> float:
    return _checked(values.positive, value, source, path)


def _nonnegative(value, source, path) -> float:
    return _checked(values.nonnegative, value, source, path)


def _numbers(value, count: int, source, path, check=_number) -> list[float]:
    _list(value, source, path, f"a list of {count} numbers")
    if len(value) != count:
        _fail(source, path, f"expected {count} numbers, got {len(value)}")
    return [check(v, source, (path, i)) for i, v in enumerate(value)]


def _integer(value, lo: int, hi: int, source, path) -> int:
    return _checked(values.integer, value, source, path, lo, hi)


def _name(value, source, path, what: str) -> str:
    if not isinstance(value, str) or not value:
        _fail(source, path, f"expected {what} (a non-empty string), got {_describe(value)}")
    return value


# ---- Primitives: parameter checks (read) and parameters (write) ----

def _size(value, source, path):
    if isinstance(value, (list, tuple)):
        return tuple(_numbers(value, 3, source, path, _positive))
    return _positive(value, source, path)


def _planes(value, source, path):
    _list(value, source, path, "a list of planes [nx, ny, nz, d]")
    top = MAX_PLANES
    if not 4 <= len(value) <= top:
        _fail(source, path, f"a closed convex solid needs 4..{top} planes, got {len(value)}")
    rows = []
    for i, row in enumerate(value):
        row = _numbers(row, 4, source, (path, i))
        if row[0] == row[1] == row[2] == 0:
            _fail(source, (path, i), "the normal (nx, ny, nz) is zero")
        rows.append(row)
    return rows


def _sides(value, source, path):
    return _integer(value, 3, 1000, source, path)


def _vertices(value, source, path):
    _list(value, source, path, "a list of vertices [x, y, z]")
    return [_numbers(row, 3, source, (path, i)) for i, row in enumerate(value)]


def _faces(value, source, path):
    _list(value, source, path, "a list of triangles [i, j, k] (vertex indices)")
    rows = []
    for i, row in enumerate(value):
        _list(row, source, (path, i), "a triangle [i, j, k]")
        if len(row) != 3:
            _fail(source, (path, i), f"expected 3 vertex indices, got {len(row)}")
        rows.append([_integer(v, 0, 2**31 - 1, source, ((path, i), k)) for k, v in enumerate(row)])
    return rows


# What a file must give for each kind of primitive parameter (`Primitive.file_parameters`).
_CHECKS = {"positive": _positive, "nonnegative": _nonnegative, "size": _size, "sides": _sides, "planes": _planes,
           "vertices": _vertices, "faces": _faces}
# type name -> (class, {parameter: check}), from the primitive classes themselves, by name
# (importing the model package defines them all)
PRIMITIVES = {name: (cls, {key: _CHECKS[kind] for key, kind in cls.file_parameters.items()})
              for name, cls in sorted(PRIMITIVE_TYPES.items())}
NODE_TYPES = (*PRIMITIVES, *OPERATIONS)
_COMMON_KEYS = ("transform", "material")
_STEPS = ("translate", "rotate", "scale", "matrix")


def _primitive_params(prim) -> tuple[str, dict]:
    """(type name, parameters) of a primitive, for writing."""
    kind = type(prim).file_type() if isinstance(prim, Primitive) else None
    if kind is None:
        raise ModelError(f"native format: cannot write a {type(prim).__name__} (not a known primitive or operation)")
    return kind, prim.parameters()


def _make_primitive(kind: str, params: dict, source, path):
    cls = PRIMITIVES[kind][0]
    try:
        prim = cls(**params)
    except (ModelError, ValueError, ArithmeticError, np.linalg.LinAlgError) as e:
        _fail(source, path, str(e))
    if kind == "convex_polyhedron":
        prim = _keep_unit_planes(prim, params["planes"])
    return prim


def _keep_unit_planes(prim, rows):
    """Keep the file's planes when they are unit already, so that saving and loading is exact.

    The constructor divides each plane by the length of its normal; for a normal of length
    1 +- an ulp that division can move the last bit, which would make every save/load round
    trip drift. Planes this close to the constructor's are the same planes.
    """
    given = np.array(rows, dtype=np.float64)
    if np.array_equal(given, prim.planes):
        return prim
    scale = np.maximum(1.0, np.abs(given))
    if np.all(np.abs(given - prim.planes) <= 8 * np.finfo(np.float64).eps * scale):
        given.setflags(write=False)
        return prim._with(planes=given)
    return prim


# ---- Transforms ----

def _matrix(value, source, path) -> np.ndarray:
    _list(value, source, path, "a 4x4 matrix (a list of 4 rows of 4 numbers)")
    if len(value) != 4:
        _fail(source, path, f"expected a 4x4 matrix (4 rows of 4 numbers), got {len(value)} rows")
    return np.array([_numbers(row, 4, source, (path, i)) for i, row in enumerate(value)])


def _transform_steps(spec, source, path) -> list[tuple]:
    """Parse a "transform" value into steps (verb, argument, path), applied first to last."""
    _list(spec, source, path, 'a 4x4 matrix or a list of steps such as {"translate": [x, y, z]}')
    if spec and isinstance(spec[0], (list, tuple)):
        return [("matrix", _matrix(spec, source, path), path)]
    steps = []
    for i, step in enumerate(spec):
        at = (path, i)
        if not isinstance(step, dict):
            _fail(source, at, 'expected a step such as {"translate": [x, y, z]} or a 4x4 matrix, '
                              f"got {_describe(step)}")
        _object(step, source, at, "a transform step")
        if len(step) != 1:
            _fail(source, at, f"a step has exactly one key ({', '.join(_STEPS)}), got {len(step)}: "
                              f"{_keys_text(step)}")
        (verb, arg), = step.items()
        if verb not in _STEPS:
            _fail(source, at, f"unknown transform step {_key(verb)}; expected one of {', '.join(_STEPS)}")
        at = (at, verb)
        if verb == "translate":
            steps.append((verb, _numbers(arg, 3, source, at), at))
        elif verb == "scale":
            if isinstance(arg, (list, tuple)):
                factors = _numbers(arg, 3, source, at)
            else:
                factors = _number(arg, source, at)
            if np.any(np.asarray(factors) == 0):
                _fail(source, at, f"a zero factor makes the solid flat, got {factors}")
            steps.append((verb, factors, at))
        elif verb == "rotate":
            _object(arg, source, at, 'a rotation {"axis": "x" | "y" | "z" | [x, y, z], "degrees": angle}')
            missing = [k for k in ("axis", "degrees") if k not in arg]
            extra = [k for k in arg if k not in ("axis", "degrees")]
            if missing or extra:
                _fail(source, at, 'expected the keys "axis" and "degrees"'
                                  + (f"; missing {_keys_text(missing)}" if missing else "")
                                  + (f"; unknown {_keys_text(extra)}" if extra else ""))
            axis = arg["axis"]
            if isinstance(axis, str):
                if axis not in ("x", "y", "z"):
                    _fail(source, (at, "axis"), f'expected "x", "y", "z" or [x, y, z], got {_describe(axis)}')
            else:
                axis = _numbers(axis, 3, source, (at, "axis"))
                if axis == [0.0, 0.0, 0.0]:
                    _fail(source, (at, "axis"), "the axis must not be the zero vector")
            steps.append((verb, (axis, _number(arg["degrees"], source, (at, "degrees"))), at))
        else:
            steps.append((verb, _matrix(arg, source, at), at))
    return steps


_TRANSFORM_PREFIX = re.compile(r"^(transform|translate|scale|rotate|rotate axis|rotate angle): ")


def _apply(node: Node, steps, material, source) -> Node:
    for verb, arg, at in steps:
        try:
            if verb == "matrix":
                node = node.transform(arg)
            elif verb == "translate":
                node = node.translate(arg)
            elif verb == "scale":
                node = node.scale(arg)
            else:
                node = node.rotate(*arg)
        except (ModelError, ValueError, ArithmeticError, np.linalg.LinAlgError) as e:
            _fail(source, at, _TRANSFORM_PREFIX.sub("", str(e)))
    if any(verb == "scale" for verb, _, _ in steps):
        # Node.scale accepts any non-zero factors; a file must not make a matrix that a saved
        # copy of it could not be read back with (see tf.affine).
        try:
            tf.check_invertible(node.matrix, "transform")
        except ModelError as e:
            _fail(source, steps[-1][2][0][0], _TRANSFORM_PREFIX.sub("", str(e)))
    if material is not None:
        node = node.with_material(material)
    return node


# ---- Reading: document -> Node ----

def _materials(value, source) -> dict:
    path = (None, "materials")
    _object(value, source, path, "a map from material names to Mitsuba BSDF dicts")
    for name, bsdf in value.items():
        at = (path, name) if isinstance(name, str) else path
        _name(name, source, at, "a material name")
        _object(bsdf, source, at, 'a Mitsuba BSDF dict such as {"type": "diffuse"}')
        if "type" not in bsdf:
            _fail(source, at, 'missing key "type" (the Mitsuba BSDF plugin, e.g. "diffuse")')
        _name(bsdf["type"], source, (at, "type"), "a Mitsuba plugin name")
        _plain_json(bsdf, source, at)
    return value


def _plain_json(value, source, path) -> None:
    """Refuse what JSON cannot hold: NaN/Infinity, non-string keys, other Python objects; bound nesting."""
    stack = [(value, path, 0)]
    while stack:
        v, at, depth = stack.pop()
        if depth > MAX_MATERIAL_DEPTH:
            _fail(source, at, f"nested deeper than {MAX_MATERIAL_DEPTH} levels")
        if isinstance(v, dict):
            _object(v, source, at, "an object")
            for k, item in v.items():
                if not isinstance(k, str):
                    _fail(source, at, f"keys must be strings, got {_describe(k)}")
                stack.append((item, (at, k), depth + 1))
        elif isinstance(v, (list, tuple)):
            stack.extend((item, (at, i), depth + 1) for i, item in enumerate(v))
        elif isinstance(v, (int, float, np.integer, np.floating, _NonFinite)) and not isinstance(v, bool):
            _number(v, source, at)
        elif not (v is None or isinstance(v, (str, bool))):
            _fail(source, at, f"expected a JSON value, got {_describe(v)}")


def _document(data, source) -> tuple[Node, dict | None]:
    _object(data, source, None, 'a model document {"format": "mitsuba-csg", "version": 1, "root": ...}')
    if "format" not in data:
        _fail(source, None, 'missing key "format"; a native model starts with '
                            '{"format": "mitsuba-csg", "version": 1, ...}')
    if data["format"] != FORMAT:
        _fail(source, (None, "format"), f'expected "{FORMAT}", got {_describe(data["format"])}')
    if "version" not in data:
        _fail(source, None, f'missing key "version" (this reader supports version '
                            f'{", ".join(map(str, SUPPORTED_VERSIONS))})')
    version = data["version"]
    supported = ", ".join(map(str, SUPPORTED_VERSIONS))
    if isinstance(version, bool) or not isinstance(version, int):
        _fail(source, (None, "version"), f"expected an integer version, got {_describe(version)}; "
                                         f"this reader supports version {supported}")
    if version not in SUPPORTED_VERSIONS:
        _fail(source, (None, "version"), f"unsupported version {version}; this reader supports version {supported}")
    extra = [k for k in data if k not in ("format", "version", "materials", "root")]
    if extra:
        _fail(source, None, f"unknown key(s) {_keys_text(extra)}; allowed keys: format, version, materials, root")
    if "root" not in data:
        _fail(source, None, 'missing key "root" (the CSG tree)')
    materials = _materials(data["materials"], source) if "materials" in data else None
    return _tree(data["root"], source, materials), materials


def _tree(root, source, materials) -> Node:
    """Check and build the node tree with an explicit stack (post-order), bounded in depth and size."""
    max_depth, max_nodes = MAX_DEPTH, MAX_NODES
    nodes = 1
    built: list[Node] = []
    # ("visit", data, path, depth) or ("build", kind, child count, steps, material, path)
    stack: list[tuple] = [("visit", root, (None, "root"), 0)]
    while stack:
        item = stack.pop()
        if item[0] == "build":
            _, kind, count, steps, material, path = item
            children = built[len(built) - count:]
            del built[len(built) - count:]
            try:
                node = Operation(kind, children)
            except ModelError as e:
                _fail(source, path, str(e))
            built.append(_apply(node, steps, material, source))
            continue

        _, data, path, depth = item
        _object(data, source, path, f"a node ({', '.join(NODE_TYPES)})")
        kind = data.get("type")
        if kind is None:
            _fail(source, path, f'missing key "type"; known node types: {", ".join(NODE_TYPES)}')
        if not isinstance(kind, str) or kind not in NODE_TYPES:
            _fail(source, (path, "type"), f"unknown node type {_key(kind)}; "
                                          f"known node types: {', '.join(NODE_TYPES)}")
        params = PRIMITIVES[kind][1] if kind in PRIMITIVES else {"children": None}
        allowed = ("type", *params, *_COMMON_KEYS)
        extra = [k for k in data if k not in allowed]
        if extra:
            _fail(source, path, f"unknown key(s) {_keys_text(extra)} for a {kind}; "
                                f"allowed keys: {', '.join(allowed)}")
        missing = [k for k in params if k not in data]
        if missing:
            _fail(source, path, f"a {kind} needs {_keys_text(missing)} (missing)")
        steps = _transform_steps(data["transform"], source, (path, "transform")) if "transform" in data else ()
        material = None
        if "material" in data:
            material = _name(data["material"], source, (path, "material"), "a material name")
            if materials is not None and material not in materials:
                known = _names_text(sorted(materials)) if materials else "none"
                _fail(source, (path, "material"), f"unknown material {_quoted(material)}; "
                                                  f'"materials" defines: {known}')

        if kind in PRIMITIVES:
            values = {k: check(data[k], source, (path, k)) for k, check in params.items()}
            built.append(_apply(_make_primitive(kind, values, source, path), steps, material, source))
            continue

        children = _list(data["children"], source, (path, "children"), "a list of child nodes")
        if not children:
            _fail(source, (path, "children"), f"a {kind} needs at least one child, got none")
        if depth + 1 > max_depth:
            _fail(source, (path, "children"), f"the tree is nested deeper than {max_depth} operation levels "
                                              "(the limit); use n-ary operations for long chains")
        nodes += len(children)
        if nodes > max_nodes:
            _fail(source, (path, "children"), f"the document has more than {max_nodes} nodes (the limit)")
        stack.append(("build", kind, len(children), steps, material, path))
        stack.extend(("visit", children[i], ((path, "children"), i), depth + 1)
                     for i in range(len(children) - 1, -1, -1))
    return built[0]


def from_dict(data, source: str = "<dict>") -> Node:
    """The model of a native document given as a dict (as `json.load` returns it)."""
    return _document(data, source)[0]


def from_dict_with_materials(data, source: str = "<dict>") -> tuple[Node, dict]:
    """(model, materials) of a native document dict; materials maps names to BSDF dicts ({} if none)."""
    node, materials = _document(data, source)
    return node, copy.deepcopy(materials) if materials is not None else {}


# ---- Reading: file -> document ----

def _read_text(path) -> tuple[str, str]:
    raw, source = read_model_bytes(path, MAX_FILE_BYTES)
    # Every node has a "type": counting them costs one pass over the bytes, no parsing.
    nodes = raw.count(b'"type"')
    memory.require(len(raw) * memory.BYTES_PER_JSON_BYTE + nodes * memory.BYTES_PER_JSON_NODE,
                   f"{source}: reading {len(raw)} bytes of JSON ({nodes} nodes)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise FormatError(f"{source}: not UTF-8 text (invalid byte at offset {e.start}, line {line}); "
                          "a native model file is UTF-8 JSON") from None
    return text.removeprefix("\ufeff"), source


def _json_integer(digits: str):
    """A JSON integer; one with more digits than Python converts (4300) stays a marker that
    the value checks name at its path, like NaN or Infinity (no float holds it anyway)."""
    if len(digits) > _MAX_INT_DIGITS:
        return _NonFinite(f"a {len(digits.lstrip('-'))}-digit integer")
    return int(digits)


_MAX_INT_DIGITS = 4000


def _parse(text: str, source: str):
    try:
        return json.loads(text, parse_constant=_NonFinite, parse_int=_json_integer, object_pairs_hook=_object_pairs)
    except RecursionError:
        pass                                            # too deep for the C scanner: go iterative
    except json.JSONDecodeError as e:
        raise FormatError(f"{source}: invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    except ValueError as e:                            # e.g. an integer with more than 4300 digits
        raise FormatError(f"{source}: invalid JSON: {e}") from None
    try:
        return _parse_iteratively(text, 2 * MAX_DEPTH + 32)
    except json.JSONDecodeError as e:
        raise FormatError(f"{source}: invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None


_WHITESPACE = re.compile(r"[ \t\n\r]*")
_NUMBER = re.compile(r"(-?(?:0|[1-9][0-9]*))(\.[0-9]+)?([eE][-+]?[0-9]+)?")
_LITERALS = (("null", None), ("true", True), ("false", False))


def _parse_iteratively(text: str, max_nesting: int):
    """json.loads (same hooks, same errors) with an explicit stack instead of recursion."""
    Error = json.JSONDecodeError
    ws = _WHITESPACE.match
    stack: list[list] = []        # [items, key] per open container; key None for arrays

    def key_at(pos):               # '"key" :' -> (key, position of the value)
        if text[pos:pos + 1] != '"':
            raise Error("Expecting property name enclosed in double quotes", text, pos)
        key, pos = scanstring(text, pos + 1)
        pos = ws(text, pos).end()
        if text[pos:pos + 1] != ":":
            raise Error("Expecting ':' delimiter", text, pos)
        return key, ws(text, pos + 1).end()

    pos = ws(text, 0).end()
    while True:
        # ---- One value at `pos` ----
        ch = text[pos:pos + 1]
        if ch in ("{", "["):
            if len(stack) >= max_nesting:
                raise Error(f"nested deeper than {max_nesting} levels (a model may nest at most "
                            f"{MAX_DEPTH} operations)", text, pos)
            after = ws(text, pos + 1).end()
            if text[after:after + 1] == ("}" if ch == "{" else "]"):
                value, pos = (_object_pairs([]) if ch == "{" else []), after + 1
            elif ch == "{":
                key, pos = key_at(after)
                stack.append([[], key])
                continue
            else:
                stack.append([[], None])
                pos = after
                continue
        elif ch == '"':
            value, pos = scanstring(text, pos + 1)
        else:
            for word, literal in _LITERALS:
                if text.startswith(word, pos):
                    value, pos = literal, pos + len(word)
                    break
            else:
                m = _NUMBER.match(text, pos)
                if m:
                    integer, frac, exp = m.groups()
                    try:
                        value = float(integer + (frac or "") + (exp or "")) if frac or exp else _json_integer(integer)
                    except ValueError as e:
                        raise Error(str(e), text, pos) from None
                    pos = m.end()
                else:
                    for word in ("NaN", "Infinity", "-Infinity"):
                        if text.startswith(word, pos):
                            value, pos = _NonFinite(word), pos + len(word)
                            break
                    else:
                        raise Error("Expecting value", text, pos)

        # ---- Hand the value to the open containers, closing those that end here ----
        while True:
            pos = ws(text, pos).end()
            if not stack:
                if pos != len(text):
                    raise Error("Extra data", text, pos)
                return value
            top = stack[-1]
            is_object = top[1] is not None
            top[0].append((top[1], value) if is_object else value)
            ch = text[pos:pos + 1]
            if ch == ",":
                if is_object:
                    top[1], pos = key_at(ws(text, pos + 1).end())
                else:
                    pos = ws(text, pos + 1).end()
                break
            if ch == ("}" if is_object else "]"):
                stack.pop()
                value = _object_pairs(top[0]) if is_object else top[0]
                pos += 1
                continue
            raise Error("Expecting ',' delimiter", text, pos)


def load(path) -> Node:
    """Read a native `.json` model file; a FormatError names the file and the JSON path of any problem."""
    return load_with_materials(path)[0]


def load_with_materials(path) -> tuple[Node, dict]:
    """(model, materials) of a native `.json` file; materials maps names to BSDF dicts ({} if none)."""
    text, source = _read_text(path)
    node, materials = _document(_parse(text, source), source)
    return node, materials if materials is not None else {}


def loads(text: str | bytes, source: str = "<string>") -> Node:
    """The model of a native document given as JSON text (e.g. inline in a scene)."""
    return loads_with_materials(text, source)[0]


def loads_with_materials(text: str | bytes, source: str = "<string>") -> tuple[Node, dict]:
    """(model, materials) of a native document given as JSON text; materials {} if none."""
    if isinstance(text, (bytes, bytearray)):
        try:
            text = bytes(text).decode("utf-8")
        except UnicodeDecodeError as e:
            raise FormatError(f"{source}: not UTF-8 text (invalid byte at offset {e.start})") from None
    if not isinstance(text, str):
        raise FormatError(f"{source}: expected JSON text, got {type(text).__name__}")
    node, materials = _document(_parse(text.removeprefix("\ufeff"), source), source)
    return node, materials if materials is not None else {}


# ---- Writing: Node -> document -> text ----

def to_dict(model: Node, materials: dict | None = None) -> dict:
    """The native document of `model` (a dict ready for `json.dump`).

    `materials` (optional) maps the material names that the model uses to Mitsuba BSDF dicts;
    when given, it must define every name the model uses, and it is written as "materials".
    Each node keeps its parameters, its operands (n-ary stays n-ary) and its local matrix,
    written as a 4x4 list when it is not the identity.
    """
    if not isinstance(model, Node):
        raise ModelError(f"to_dict: expected a CSG node, got {type(model).__name__}")
    doc: dict = {"format": FORMAT, "version": VERSION}
    if materials is not None:
        _materials(materials, "to_dict")
        doc["materials"] = copy.deepcopy(materials)

    used: set[str] = set()
    holder: list = []
    written: list = []          # (matrix, depth-first node index, type) of every transform written
    nodes, visited = 1, 0
    stack = [(model, holder, 0)]
    while stack:
        node, siblings, depth = stack.pop()
        if isinstance(node, Operation):
            out = {"type": node.kind}
        else:
            kind, params = _primitive_params(node)
            out = {"type": kind, **params}
        if node.matrix is not tf.IDENTITY and not np.array_equal(node.matrix, tf.IDENTITY):
            out["transform"] = node.matrix.tolist()
            written.append((node.matrix, visited, out["type"]))
        visited += 1
        if node.material is not None:
            out["material"] = node.material
            used.add(node.material)
        siblings.append(out)
        if isinstance(node, Operation):
            if depth + 1 > MAX_DEPTH:
                raise ModelError(f"to_dict: the tree is nested deeper than {MAX_DEPTH} operation levels, "
                                 "which files may not exceed; use n-ary operations for long chains")
            nodes += len(node.children)
            if nodes > MAX_NODES:
                raise ModelError(f"to_dict: the model has more than {MAX_NODES} nodes (counting shared "
                                 "subtrees once per use), which files may not exceed")
            out["children"] = []
            stack.extend((c, out["children"], depth + 1) for c in reversed(node.children))
    if materials is not None and not used <= set(materials):
        missing = ", ".join(sorted(used - set(materials)))
        raise ModelError(f"to_dict: the model uses material(s) {missing} that `materials` does not define")
    _check_readable(written)
    doc["root"] = holder[0]
    return doc


def _check_readable(written) -> None:
    """Refuse matrices that `load` would refuse (products of extreme scales can be singular or overflow)."""
    if not written:
        return
    mats = np.array([m for m, _, _ in written])
    with np.errstate(all="ignore"):
        ok = np.all(np.isfinite(mats), axis=(1, 2))
        sv = np.zeros((len(mats), 3))
        sv[ok] = np.linalg.svd(mats[ok, :3, :3], compute_uv=False)
        ok &= np.all(np.isfinite(sv), axis=1) & (sv[:, 2] > sv[:, 0] * 1e-12)
    if not np.all(ok):
        matrix, index, kind = written[int(np.argmin(ok))]
        raise ModelError(f"to_dict: node {index} (depth-first order, a {kind}) has a local matrix that a file "
                         f"cannot hold (non-finite or singular: {matrix[:3].tolist()}); "
                         "its transforms multiply to a degenerate matrix")


_INDENT_CAP = 40            # deeper levels are not indented further (files stay linear in size)


def _inline(value) -> str:
    return json.dumps(value, separators=(", ", ": "), allow_nan=False)


def _document_text(doc: dict) -> str:
    """The document as text: one line per primitive and material, operations spread over lines."""
    out = ["{\n"]
    for key, value in doc.items():
        if key == "root":
            continue
        if key == "materials" and value:
            entries = ",\n".join(f"    {json.dumps(name)}: {_inline(bsdf)}" for name, bsdf in value.items())
            out.append(f'  "materials": {{\n{entries}\n  }},\n')
        else:
            out.append(f"  {json.dumps(key)}: {_inline(value)},\n")
    out.append('  "root": ')
    stack: list = [(doc["root"], 1)]      # a node dict and its level, or literal text
    while stack:
        item = stack.pop()
        if isinstance(item, str):
            out.append(item)
            continue
        node, level = item
        if "children" not in node:
            out.append(_inline(node))
            continue
        head = _inline({k: v for k, v in node.items() if k != "children"})
        out.append(head[:-1] + ', "children": [\n')
        pad, inner = "  " * min(level, _INDENT_CAP), "  " * min(level + 1, _INDENT_CAP)
        children = node["children"]
        stack.append(f"\n{pad}]}}")
        for i in range(len(children) - 1, -1, -1):
            if i < len(children) - 1:
                stack.append(",\n")
            stack.append((children[i], level + 1))
            stack.append(inner)
    out.append("\n}\n")
    return "".join(out)


def save(model: Node, path, materials: dict | None = None) -> None:
    """Write `model` (and optionally its `materials`, name -> Mitsuba BSDF dict) as a native `.json` file."""
    text = _document_text(to_dict(model, materials))
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)


__all__ = ["FormatError", "from_dict", "from_dict_with_materials", "load", "load_with_materials", "loads",
           "loads_with_materials", "save", "to_dict"]
