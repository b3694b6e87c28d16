"""Geant4 GDML files (`.gdml`): defines, solids, structure and setup as a CSG model.

    load(path, *, solid=None, depth=None, show_world=False, on_unsupported="error") -> Node
    loads(text, source="<string>", *, base_dir=None, **same) -> Node

Output units are **millimetres** (Geant4's internal length unit); angles are read in radians
unless `aunit`/`unit` says otherwise. Without `solid`, the result is the placed scene: the
union of every placed logical volume below the world (the world itself only with
`show_world=True`), each one its GDML solid moved to its world placement and named with its
material (the `materialref`, with Geant4's `0x...` pointer suffix stripped). Daughters are not
subtracted from their mothers: for opaque rendering the outermost level is what one sees, so
`depth=k` keeps the volumes at most k placement levels below the world (the world's daughters
are depth 1; an assembly is transparent, its contents count as daughters of the volume that
places it, as in Geant4). `solid="name"` gives one GDML solid in its own frame, no material.

What is read
------------
* `<define>`: constant, variable, quantity, expression (scalars, in document order as Geant4
  evaluates them), position, rotation, scale; `matrix` is ignored. Attribute values are
  arithmetic over numbers, defined scalars, units (mm cm m km um nm angstrom deg rad mrad ...),
  pi/e, `+ - * / ^` and sin cos tan asin acos atan atan2 sqrt exp log log10 pow abs min max;
  evaluated by a whitelisted `ast` walker, never `eval`.
* Solids: box, tube, cutTube, cone, sphere, orb, torus, polycone, polyhedra (zplane rmax is
  the apothem), trd, trap, para, ellipsoid, eltube, elcone, union, subtraction, intersection,
  multiUnion, scaledSolid. Phi segments are intersections with (or, above 180 degrees,
  subtractions of) convex wedges; rmin holes are subtracted cones/spheres/tori extended past
  the caps so no faces coincide; theta cuts are cones with their apex at the centre.
* Not representable exactly by our primitives: tessellated, xtru, tet, arb8, twisted*, hype,
  paraboloid, genericPolycone, genericPolyhedra, reflectedSolid, opticalsurface-bound solids,
  replicavol/paramvol/divisionvol, loops and `physvol file=`. `on_unsupported="error"` raises a
  FormatError naming the element and its name; `"skip"` warns (UserWarning) and leaves the solid
  out, together with every boolean built from it and every volume made of it.

Transform conventions (Geant4 10/11, `G4GDMLReadDefine::GetRotationMatrix`): a `<rotation>`
x, y, z builds R = Rz(z) Ry(y) Rx(x) (CLHEP `rotateX` then `rotateY` then `rotateZ`, each a
left multiplication, right-handed and active). `G4GDMLReadSolids::BooleanRead` builds
`G4Transform3D(R, t)` for `second` (and for `firstposition/firstrotation`, multiUnion nodes):
the operand moves by x' = R x + t. `G4GDMLReadStructure::PhysvolRead` builds
`G4Transform3D(R.inverse(), t) * G4Scale3D(s)`: a daughter moves by x' = R^-1 (s x) + t; the
GDML rotation of a physvol is the frame rotation, i.e. the inverse of the object rotation.

Files are untrusted input: every problem is a `FormatError` whose message starts with the
source and the line and element, e.g. `det.gdml: line 12: <tube name="t1">: rmax: must be > 0`.
XML is parsed by expat with a DOCTYPE policy: internal entities are allowed but may not refer
to other entities (the entity-expansion bomb pattern) and are size-bounded; external entities
(`<!ENTITY m SYSTEM "materials.xml">`, Geant4's G01 example) are read only from files in the
document's directory or below it, never from the network; parameter entities and external DTDs
are not read. Element counts, text size, nesting and placement counts are bounded.
"""
from __future__ import annotations

import ast
import itertools
import math
import os
import re
import warnings
import xml.etree.ElementTree as ET
import xml.parsers.expat as expat

import numpy as np

from . import transform as tf
from .errors import ModelError
from .model import Node, Operation
from .native import FormatError, read_model_bytes
from .primitives import Box, Cone, ConvexPolyhedron, Cylinder, Sphere, Torus

__all__ = ["FormatError", "UNITS", "load", "loads"]

MAX_FILE_BYTES = 1 << 30           # one document (external entities included)
MAX_ELEMENTS = 5_000_000           # XML elements, after entity expansion
MAX_TEXT_CHARS = 50_000_000        # character data, after entity expansion
MAX_ENTITY_CHARS = 1 << 16         # replacement text of one internal entity
MAX_EXTERNAL_ENTITIES = 256        # external entity references in one document
MAX_ENTITY_NESTING = 8             # external entities referenced from external entities
MAX_EXPRESSION_CHARS = 10_000      # one attribute expression
MAX_EXPRESSION_DEPTH = 200         # nesting of one expression's syntax tree
MAX_PLACEMENTS = 2_000_000         # placed volumes in the scene
MAX_VOLUME_DEPTH = 10_000          # placement levels
TWO_PI = 2.0 * math.pi

# ---- Units (CLHEP values: mm, rad, ns, MeV, eplus are 1) ----
_e_SI = 1.602176634e-19
_joule = 1e-6 / _e_SI                # electronvolt / e_SI, electronvolt = 1e-6 MeV
_kg = _joule * 1e12                  # joule * s^2 / m^2 with s = 1e9 ns, m = 1e3 mm
UNITS = {
    # length
    "mm": 1.0, "millimeter": 1.0, "cm": 10.0, "centimeter": 10.0, "m": 1000.0, "meter": 1000.0,
    "km": 1e6, "kilometer": 1e6, "um": 1e-3, "micrometer": 1e-3, "nm": 1e-6, "nanometer": 1e-6,
    "angstrom": 1e-7, "fermi": 1e-12, "pc": 3.0856775807e16 * 1000.0, "parsec": 3.0856775807e16 * 1000.0,
    "mm2": 1.0, "cm2": 100.0, "m2": 1e6, "km2": 1e12, "mm3": 1.0, "cm3": 1e3, "m3": 1e9, "km3": 1e18,
    "L": 1e6, "dL": 1e5, "cL": 1e4, "mL": 1e3,
    # angle
    "rad": 1.0, "radian": 1.0, "mrad": 1e-3, "milliradian": 1e-3, "deg": math.pi / 180.0,
    "degree": math.pi / 180.0, "sr": 1.0, "steradian": 1.0,
    # time, energy, mass, amount, temperature, pressure (materials; never geometry)
    "ns": 1.0, "s": 1e9, "ms": 1e6, "us": 1e3, "ps": 1e-3, "second": 1e9,
    "MeV": 1.0, "eV": 1e-6, "keV": 1e-3, "GeV": 1e3, "TeV": 1e6, "PeV": 1e9,
    "joule": _joule, "kg": _kg, "kilogram": _kg, "g": _kg * 1e-3, "gram": _kg * 1e-3, "mg": _kg * 1e-6,
    "mole": 1.0, "mol": 1.0, "kelvin": 1.0, "K": 1.0, "perCent": 0.01, "perThousand": 1e-3,
    "perMillion": 1e-6, "pascal": _joule / 1e9, "bar": 1e5 * _joule / 1e9, "atmosphere": 101325 * _joule / 1e9,
    "eplus": 1.0, "e_SI": _e_SI,
}
_CONSTANTS = {"pi": math.pi, "e": math.e, "twopi": TWO_PI, "halfpi": 0.5 * math.pi, "pi2": math.pi ** 2}
_FUNCTIONS = {
    "sin": (math.sin, 1), "cos": (math.cos, 1), "tan": (math.tan, 1), "asin": (math.asin, 1),
    "acos": (math.acos, 1), "atan": (math.atan, 1), "atan2": (math.atan2, 2), "sinh": (math.sinh, 1),
    "cosh": (math.cosh, 1), "tanh": (math.tanh, 1), "sqrt": (math.sqrt, 1), "exp": (math.exp, 1),
    "log": (math.log, 1), "log10": (math.log10, 1), "pow": (math.pow, 2), "abs": (abs, 1),
    "fabs": (abs, 1), "min": (min, 2), "max": (max, 2),
}

# Solids we know Geant4 has but cannot represent exactly with our primitives.
UNSUPPORTED_SOLIDS = (
    "tessellated", "xtru", "tet", "arb8", "twistedbox", "twistedtrd", "twistedtrap", "twistedtubs",
    "hype", "paraboloid", "genericPolycone", "genericPolyhedra", "reflectedSolid", "loop",
    "gencone",
)
_BOOLEANS = {"union": "union", "subtraction": "difference", "intersection": "intersection"}


class _ParseAbort(Exception):
    """Raised inside expat handlers; turned into a FormatError with the line."""


# ---- XML with a DOCTYPE policy ----

def _parse_xml(data: bytes, source: str, base_dir: str | None):
    """The root element and {id(element): line}, or FormatError."""
    builder = ET.TreeBuilder()
    lines: dict[int, int] = {}
    state = {"elements": 0, "text": 0, "external": 0, "nesting": 0, "bytes": len(data)}
    parser = expat.ParserCreate()

    def start(tag, attrs):
        state["elements"] += 1
        if state["elements"] > MAX_ELEMENTS:
            raise _ParseAbort(f"more than {MAX_ELEMENTS} elements (after entity expansion)")
        el = builder.start(tag, attrs)
        lines[id(el)] = parser.CurrentLineNumber

    def data_(text):
        state["text"] += len(text)
        if state["text"] > MAX_TEXT_CHARS:
            raise _ParseAbort(f"more than {MAX_TEXT_CHARS} characters of text (after entity expansion)")
        builder.data(text)

    def entity_decl(name, is_parameter, value, base, system_id, public_id, notation):
        if is_parameter:
            raise _ParseAbort(f"parameter entity %{name}; is not supported")
        if notation is not None:
            raise _ParseAbort(f"unparsed entity {name!r} (NDATA) is not supported")
        if value is not None:
            if "&" in value or "%" in value:
                raise _ParseAbort(f"entity {name!r} refers to other entities; nested entities are refused "
                                  f"(the entity-expansion bomb pattern)")
            if len(value) > MAX_ENTITY_CHARS:
                raise _ParseAbort(f"entity {name!r} is {len(value)} characters long (limit {MAX_ENTITY_CHARS})")
        else:
            _local_entity_path(system_id, base_dir, name)   # refuse early

    def external(context, base, system_id, public_id):
        name = (context or "").rsplit("\x0c", 1)[-1] or system_id
        path = _local_entity_path(system_id, base_dir, name)
        state["external"] += 1
        if state["external"] > MAX_EXTERNAL_ENTITIES:
            raise _ParseAbort(f"more than {MAX_EXTERNAL_ENTITIES} external entity references")
        if state["nesting"] >= MAX_ENTITY_NESTING:
            raise _ParseAbort(f"external entity {name!r} nested more than {MAX_ENTITY_NESTING} deep "
                              f"(an entity that includes itself?)")
        try:
            with open(path, "rb") as f:
                content = f.read(MAX_FILE_BYTES + 1)
        except OSError as e:
            raise _ParseAbort(f"external entity {name!r}: cannot read {system_id!r}: {e.strerror or e}") from None
        state["bytes"] += len(content)
        if state["bytes"] > MAX_FILE_BYTES:
            raise _ParseAbort(f"document with its entities exceeds {MAX_FILE_BYTES} bytes")
        sub = parser.ExternalEntityParserCreate(context)
        state["nesting"] += 1
        try:
            sub.Parse(content, True)
        except expat.ExpatError as e:
            raise _ParseAbort(f"external entity {name!r} ({system_id}): line {e.lineno}: malformed XML: "
                              f"{expat.ErrorString(e.code)}") from None
        finally:
            state["nesting"] -= 1
        return 1

    parser.StartElementHandler = start
    parser.EndElementHandler = builder.end
    parser.CharacterDataHandler = data_
    parser.EntityDeclHandler = entity_decl
    parser.ExternalEntityRefHandler = external
    try:
        parser.Parse(data, True)
        root = builder.close()
    except expat.ExpatError as e:
        raise FormatError(f"{source}: line {e.lineno}: malformed XML: {expat.ErrorString(e.code)}") from None
    except _ParseAbort as e:
        raise FormatError(f"{source}: line {parser.CurrentLineNumber}: {e}") from None
    except (RecursionError, MemoryError):
        raise FormatError(f"{source}: line {parser.CurrentLineNumber}: XML nested too deeply") from None
    except AssertionError:   # TreeBuilder on inconsistent input
        raise FormatError(f"{source}: malformed XML") from None
    except (LookupError, UnicodeError, ValueError) as e:   # e.g. an unknown encoding="..." declaration
        raise FormatError(f"{source}: line {parser.CurrentLineNumber}: cannot read the XML: {e}") from None
    return root, lines


def _local_entity_path(system_id, base_dir, name) -> str:
    if not system_id:
        raise _ParseAbort(f"external entity {name!r} has no file name")
    if re.match(r"^[A-Za-z][A-Za-z0-9+.-]*:", system_id) and not re.match(r"^[A-Za-z]:[\\/]", system_id):
        raise _ParseAbort(f"external entity {name!r} ({system_id!r}): only local files beside the document "
                          f"are read, never URLs")
    if base_dir is None:
        raise _ParseAbort(f"external entity {name!r} ({system_id!r}): external entities are read only for "
                          f"documents loaded from a file (pass base_dir to loads)")
    if os.path.isabs(system_id):
        raise _ParseAbort(f"external entity {name!r} ({system_id!r}): absolute paths are refused; only files "
                          f"beside the document are read")
    root = os.path.realpath(base_dir)
    path = os.path.realpath(os.path.join(root, system_id))
    if os.path.commonpath([root, path]) != root:
        raise _ParseAbort(f"external entity {name!r} ({system_id!r}) points outside the document's directory")
    return path


# ---- Rotations ----

def rotation_matrix(angles) -> np.ndarray:
    """R = Rz(z) Ry(y) Rx(x) for GDML rotation angles (radians), right-handed and active."""
    x, y, z = angles
    cx, sx, cy, sy, cz, sz = math.cos(x), math.sin(x), math.cos(y), math.sin(y), math.cos(z), math.sin(z)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _affine(linear: np.ndarray, offset) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = offset
    return m


class _Unsupported(Exception):
    """A solid we cannot represent; carries the FormatError message."""


# ---- The reader ----

class _Reader:
    def __init__(self, root, lines, source: str, on_unsupported: str):
        self.root, self.lines, self.source = root, lines, source
        self.skip_unsupported = on_unsupported == "skip"
        self.scalars: dict[str, object] = {}     # name -> float, or FormatError deferred until used
        self.vectors: dict[str, dict[str, ET.Element]] = {"position": {}, "rotation": {}, "scale": {}}
        self.solid_elements: dict[str, ET.Element] = {}
        self.solids: dict[str, Node | None] = {}  # built; None = unsupported and skipped
        self.volumes: dict[str, ET.Element] = {}
        self.assemblies: dict[str, ET.Element] = {}
        self.warned: set[str] = set()
        if root.tag != "gdml":
            raise FormatError(f"{source}: line {lines.get(id(root), 1)}: the root element is <{root.tag}>, "
                              f"expected <gdml>")
        for section in root:
            if section.tag == "define":
                self._read_defines(section)
            elif section.tag == "solids":
                for el in section:
                    self._register(self.solid_elements, el, "solid")
            elif section.tag == "structure":
                for el in section:
                    if el.tag == "volume":
                        self._register(self.volumes, el, "volume")
                    elif el.tag == "assembly":
                        self._register(self.assemblies, el, "assembly")
                    elif el.tag in ("skinsurface", "bordersurface", "loop"):
                        if el.tag == "loop":
                            self._unsupported(el, "<loop> is not supported")
                    else:
                        self.fail(el, f"unknown structure element <{el.tag}>")
            elif section.tag in ("materials", "setup", "userinfo"):
                pass
            else:
                self.fail(section, f"unknown section <{section.tag}>; expected define, materials, solids, "
                                   f"structure, setup")
        for name in self.volumes.keys() & self.assemblies.keys():
            self.fail(self.assemblies[name], f"the name {name!r} is used by a volume and an assembly")

    # ---- Messages ----
    def where(self, el) -> str:
        line = self.lines.get(id(el))
        name = el.get("name")
        tag = f'<{el.tag} name="{name}">' if name is not None else f"<{el.tag}>"
        return f"{self.source}: line {line}: {tag}" if line else f"{self.source}: {tag}"

    def fail(self, el, message: str):
        raise FormatError(f"{self.where(el)}: {message}")

    def _unsupported(self, el, message: str):
        text = f"{self.where(el)}: {message}"
        if not self.skip_unsupported:
            raise FormatError(text + " (on_unsupported='skip' leaves it out)")
        if text not in self.warned:
            self.warned.add(text)
            warnings.warn(text + "; skipped", UserWarning, stacklevel=4)

    def _register(self, table, el, what):
        name = el.get("name")
        if not name:
            self.fail(el, f"a {what} needs a name attribute")
        if name in table:
            self.fail(el, f"{what} {name!r} is defined twice (first at line {self.lines.get(id(table[name]))})")
        table[name] = el

    # ---- Expressions ----
    def number(self, el, attr, default=None, unit: float = 1.0) -> float:
        text = el.get(attr)
        if text is None:
            if default is None:
                self.fail(el, f"missing attribute {attr!r}")
            return float(default)
        try:
            value = self.evaluate(text) * unit
        except FormatError as e:
            self.fail(el, f'{attr}="{_short(text)}": {e}')
        if not math.isfinite(value):
            self.fail(el, f'{attr}="{_short(text)}": the value is not finite')
        return value

    def unit(self, el, attr, default: str) -> float:
        text = el.get(attr, default)
        try:
            value = self.evaluate(text)
        except FormatError as e:
            self.fail(el, f'{attr}="{_short(text)}": {e}')
        if not math.isfinite(value) or value == 0:
            self.fail(el, f'{attr}="{_short(text)}": not a usable unit')
        return value

    def evaluate(self, text: str) -> float:
        """A GDML expression's value; FormatError with a bare message (callers add the place)."""
        s = text.strip()
        if not s:
            raise FormatError("empty expression")
        if len(s) > MAX_EXPRESSION_CHARS:
            raise FormatError(f"expression longer than {MAX_EXPRESSION_CHARS} characters")
        if "**" in s:
            raise FormatError(f"bad expression {_short(s)!r}: '**' is not GDML; use '^'")
        try:
            tree = ast.parse(s.replace("^", "**"), mode="eval")
        except (SyntaxError, ValueError, RecursionError, MemoryError, OverflowError):
            raise FormatError(f"bad expression {_short(s)!r}") from None
        try:
            value = self._walk(tree.body, 0)
        except FormatError:
            raise
        except RecursionError:
            raise FormatError(f"expression {_short(s)!r} is nested too deeply") from None
        except (ZeroDivisionError, OverflowError, ValueError) as e:
            raise FormatError(f"expression {_short(s)!r}: {e}") from None
        if not math.isfinite(value):
            raise FormatError(f"expression {_short(s)!r} is not finite")
        return value

    def _walk(self, node, depth: int) -> float:
        if depth > MAX_EXPRESSION_DEPTH:
            raise FormatError(f"expression nested more than {MAX_EXPRESSION_DEPTH} deep")
        if isinstance(node, ast.Constant):
            v = node.value
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise FormatError(f"{v!r} is not a number")
            return float(v)
        if isinstance(node, ast.Name):
            return self.lookup(node.id)
        if isinstance(node, ast.BinOp):
            a, b = self._walk(node.left, depth + 1), self._walk(node.right, depth + 1)
            op = type(node.op)
            if op is ast.Add:
                r = a + b
            elif op is ast.Sub:
                r = a - b
            elif op is ast.Mult:
                r = a * b
            elif op is ast.Div:
                r = a / b
            elif op is ast.Pow:
                r = math.pow(a, b)
            else:
                raise FormatError(f"operator {type(node.op).__name__} is not allowed")
            if not math.isfinite(r):
                raise FormatError("a result is not finite (overflow)")
            return r
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            v = self._walk(node.operand, depth + 1)
            return -v if isinstance(node.op, ast.USub) else v
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.keywords:
            fn = _FUNCTIONS.get(node.func.id)
            if fn is None:
                raise FormatError(f"unknown function {node.func.id!r}")
            if len(node.args) != fn[1] or any(isinstance(a, ast.Starred) for a in node.args):
                raise FormatError(f"{node.func.id} takes {fn[1]} argument(s), got {len(node.args)}")
            r = float(fn[0](*(self._walk(a, depth + 1) for a in node.args)))
            if not math.isfinite(r):
                raise FormatError(f"{node.func.id}(...) is not finite")
            return r
        raise FormatError(f"{type(node).__name__} is not allowed in an expression")

    def lookup(self, name: str) -> float:
        if name in self.scalars:
            v = self.scalars[name]
            if isinstance(v, FormatError):
                raise FormatError(f"{name!r} could not be evaluated: {v}")
            return v
        if name in UNITS:
            return UNITS[name]
        if name in _CONSTANTS:
            return _CONSTANTS[name]
        raise FormatError(f"undefined name {name!r} (constants must be defined before they are used)")

    # ---- <define> ----
    def _read_defines(self, section):
        for el in section:
            tag = el.tag
            if tag in ("constant", "variable", "quantity", "expression"):
                name = el.get("name")
                if not name or not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", name):
                    self.fail(el, f"a {tag} needs a name made of letters, digits and '_', got {name!r}")
                if name in self.scalars:
                    self.fail(el, f"{name!r} is defined twice")
                try:
                    if tag == "expression":
                        value = self.evaluate(el.text or "")
                    else:
                        attr = "value"
                        value = self.number(el, attr)
                        if tag == "quantity" and el.get("unit") is not None:
                            value *= self.unit(el, "unit", "1")
                except FormatError as e:
                    value = e if str(e).startswith(self.source) else FormatError(f"{self.where(el)}: {e}")
                self.scalars[name] = value
            elif tag in self.vectors:
                name = el.get("name")
                if not name:
                    self.fail(el, f"a <{tag}> in <define> needs a name")
                if name in self.vectors[tag]:
                    self.fail(el, f"{tag} {name!r} is defined twice")
                self.vectors[tag][name] = el
            elif tag == "matrix":
                pass
            else:
                self.fail(el, f"unknown define element <{tag}>")

    def vector(self, el, kind: str) -> np.ndarray:
        """x, y, z of a <position>/<rotation>/<scale> element, in mm / rad / 1."""
        if kind == "scale":
            return np.array([self.number(el, a, 1.0) for a in "xyz"])
        default = "mm" if kind == "position" else "rad"
        unit = self.unit(el, "unit" if el.get("unit") is not None else
                         ("lunit" if kind == "position" else "aunit"), default)
        return np.array([self.number(el, a, 0.0, unit) for a in "xyz"])

    def vector_ref(self, el, kind: str) -> np.ndarray:
        name = el.get("ref")
        if not name:
            self.fail(el, "needs a ref attribute")
        target = self.vectors[kind].get(name)
        if target is None:
            self.fail(el, f"refers to undefined {kind} {name!r}")
        return self.vector(target, kind)

    def placement(self, el, prefix: str = ""):
        """(translation, rotation angles, scale) from inline or referenced children of `el`."""
        found = {"position": np.zeros(3), "rotation": np.zeros(3), "scale": np.ones(3)}
        for child in el:
            tag = child.tag
            for kind in found:
                if tag == prefix + kind:
                    found[kind] = self.vector(child, kind)
                elif tag == prefix + kind + "ref":
                    found[kind] = self.vector_ref(child, kind)
        return found["position"], found["rotation"], found["scale"]

    # ---- Solids ----
    def _solid_refs(self, el) -> list[tuple[ET.Element, str]]:
        tag = el.tag
        refs = []
        if tag in _BOOLEANS:
            for part in ("first", "second"):
                child = el.find(part)
                if child is None or not child.get("ref"):
                    self.fail(el, f"needs <{part} ref=\"...\"/>")
                refs.append((child, child.get("ref")))
        elif tag == "multiUnion":
            for node in el.findall("multiUnionNode"):
                child = node.find("solid")
                if child is None or not child.get("ref"):
                    self.fail(node, "needs <solid ref=\"...\"/>")
                refs.append((child, child.get("ref")))
        elif tag == "scaledSolid":
            child = el.find("solidref")
            if child is None or not child.get("ref"):
                self.fail(el, "needs <solidref ref=\"...\"/>")
            refs.append((child, child.get("ref")))
        return refs

    def solid(self, name: str, referrer) -> Node | None:
        """The solid `name`, built with its operands (explicit stack: deep boolean chains are fine)."""
        if name in self.solids:
            return self.solids[name]
        if name not in self.solid_elements:
            self.fail(referrer, f"refers to undefined solid {name!r}")
        stack, visiting = [name], {name}
        while stack:
            current = stack[-1]
            el = self.solid_elements[current]
            pending = []
            for ref_el, ref in self._solid_refs(el):
                if ref in self.solids:
                    continue
                if ref not in self.solid_elements:
                    self.fail(ref_el, f"solid {current!r} refers to undefined solid {ref!r}")
                if ref in visiting:
                    self.fail(el, f"solid reference cycle: {' -> '.join(stack[stack.index(ref):] + [ref])}")
                pending.append(ref)
            if pending:
                for ref in dict.fromkeys(pending):
                    stack.append(ref)
                    visiting.add(ref)
                continue
            stack.pop()
            visiting.discard(current)
            self.solids[current] = self._build(el)
        return self.solids[name]

    def _build(self, el) -> Node | None:
        tag = el.tag
        builder = getattr(self, "_solid_" + tag, None)
        if builder is None:
            if tag in UNSUPPORTED_SOLIDS or tag.startswith("twisted"):
                self._unsupported(el, f"the GDML solid <{tag}> cannot be represented exactly with analytic "
                                      f"primitives")
                return None
            if tag in ("opticalsurface",):
                return None
            self._unsupported(el, f"unknown solid <{tag}>")
            return None
        try:
            return builder(el)
        except ModelError as e:
            if isinstance(e, FormatError):
                raise
            self.fail(el, str(e))

    def _units(self, el):
        return self.unit(el, "lunit", "mm"), self.unit(el, "aunit", "rad")

    def _positive(self, el, attr, unit, default=None) -> float:
        v = self.number(el, attr, default, unit)
        if v <= 0:
            self.fail(el, f"{attr}: must be > 0, got {v:g}")
        return v

    def _nonnegative(self, el, attr, unit, default=None) -> float:
        v = self.number(el, attr, default, unit)
        if v < 0:
            self.fail(el, f"{attr}: must be >= 0, got {v:g}")
        return v

    def _phi(self, el, aunit, start="startphi", delta="deltaphi"):
        phi0 = self.number(el, start, 0.0, aunit)
        dphi = self.number(el, delta, None, aunit) if el.get(delta) is not None else TWO_PI
        if dphi <= 0:
            self.fail(el, f"{delta}: must be > 0, got {dphi:g}")
        return phi0, min(dphi, TWO_PI)

    def _solid_box(self, el):
        lunit, _ = self._units(el)
        return Box([self._positive(el, a, lunit) for a in "xyz"])

    def _solid_orb(self, el):
        lunit, _ = self._units(el)
        return Sphere(self._positive(el, "r", lunit))

    def _solid_tube(self, el):
        lunit, aunit = self._units(el)
        rmin = self._nonnegative(el, "rmin", lunit, 0.0)
        rmax = self._positive(el, "rmax", lunit)
        z = self._positive(el, "z", lunit)
        if rmin >= rmax:
            self.fail(el, f"rmin ({rmin:g}) must be < rmax ({rmax:g})")
        solid = Cylinder(rmax, z)
        if rmin > 0:
            solid = solid - _inner_cone(rmin, rmin, z)
        return _phi_cut(solid, *self._phi(el, aunit), rmax, 0.5 * z)

    def _solid_cutTube(self, el):
        lunit, aunit = self._units(el)
        rmin = self._nonnegative(el, "rmin", lunit, 0.0)
        rmax = self._positive(el, "rmax", lunit)
        dz = 0.5 * self._positive(el, "z", lunit)
        if rmin >= rmax:
            self.fail(el, f"rmin ({rmin:g}) must be < rmax ({rmax:g})")
        low = np.array([self.number(el, a, 0.0) for a in ("lowX", "lowY", "lowZ")])
        high = np.array([self.number(el, a, 0.0) for a in ("highX", "highY", "highZ")])
        if not (np.linalg.norm(low) > 0 and low[2] < 0 and np.linalg.norm(high) > 0 and high[2] > 0):
            self.fail(el, "the low cut normal needs a negative z component and the high one a positive one")
        low, high = low / np.linalg.norm(low), high / np.linalg.norm(high)
        reach = dz + rmax * max(np.hypot(*low[:2]) / -low[2], np.hypot(*high[:2]) / high[2])
        height = 2.0 * reach + 2.0 * rmax
        solid = Cylinder(rmax, height)
        if rmin > 0:
            solid = solid - Cylinder(rmin, 1.5 * height)
        r, h = 2.0 * rmax, height
        cut = ConvexPolyhedron([[*low, -low[2] * dz], [*high, high[2] * dz], [1, 0, 0, r], [-1, 0, 0, r],
                                [0, 1, 0, r], [0, -1, 0, r], [0, 0, 1, h], [0, 0, -1, h]])
        return _phi_cut(solid & cut, *self._phi(el, aunit), rmax, reach)

    def _solid_cone(self, el):
        lunit, aunit = self._units(el)
        rmin1, rmin2 = (self._nonnegative(el, a, lunit, 0.0) for a in ("rmin1", "rmin2"))
        rmax1, rmax2 = (self._nonnegative(el, a, lunit, 0.0) for a in ("rmax1", "rmax2"))
        z = self._positive(el, "z", lunit)
        if rmin1 > rmax1 or rmin2 > rmax2 or (rmin1 == rmax1 and rmin2 == rmax2):
            self.fail(el, "needs rmin1 <= rmax1 and rmin2 <= rmax2, not both equal")
        solid = Cone(rmax1, rmax2, z)
        inner = _inner_cone(rmin1, rmin2, z)
        if inner is not None:
            solid = solid - inner
        return _phi_cut(solid, *self._phi(el, aunit), max(rmax1, rmax2), 0.5 * z)

    def _solid_sphere(self, el):
        lunit, aunit = self._units(el)
        rmin = self._nonnegative(el, "rmin", lunit, 0.0)
        rmax = self._positive(el, "rmax", lunit)
        if rmin >= rmax:
            self.fail(el, f"rmin ({rmin:g}) must be < rmax ({rmax:g})")
        solid = Sphere(rmax)
        if rmin > 0:
            solid = solid - Sphere(rmin)
        theta0 = self.number(el, "starttheta", 0.0, aunit)
        dtheta = self.number(el, "deltatheta", None, aunit) if el.get("deltatheta") is not None else math.pi
        if not (0 <= theta0 < math.pi) or dtheta <= 0:
            self.fail(el, f"needs 0 <= starttheta < 180 deg and deltatheta > 0, got {theta0:g} rad, {dtheta:g} rad")
        solid = _theta_cut(solid, theta0, min(theta0 + dtheta, math.pi), 2.0 * rmax)
        return _phi_cut(solid, *self._phi(el, aunit), rmax, rmax)

    def _solid_torus(self, el):
        lunit, aunit = self._units(el)
        rmin = self._nonnegative(el, "rmin", lunit, 0.0)
        rmax = self._positive(el, "rmax", lunit)
        rtor = self._positive(el, "rtor", lunit)
        if rmin >= rmax or rmax >= rtor:
            self.fail(el, f"needs rmin < rmax < rtor, got {rmin:g}, {rmax:g}, {rtor:g}")
        solid = Torus(rtor, rmax)
        if rmin > 0:
            solid = solid - Torus(rtor, rmin)
        return _phi_cut(solid, *self._phi(el, aunit), rtor + rmax, rmax)

    def _zplanes(self, el, lunit):
        planes = []
        for zp in el.findall("zplane"):
            z = self.number(zp, "z", None, lunit)
            rmin = self.number(zp, "rmin", 0.0, lunit)
            rmax = self.number(zp, "rmax", None, lunit)
            if rmin < 0 or rmax < rmin:
                self.fail(zp, f"needs 0 <= rmin <= rmax, got rmin {rmin:g}, rmax {rmax:g}")
            planes.append((z, rmin, rmax))
        if len(planes) < 2:
            self.fail(el, f"needs at least 2 <zplane> elements, got {len(planes)}")
        zs = [p[0] for p in planes]
        if not (all(a <= b for a, b in zip(zs, zs[1:])) or all(a >= b for a, b in zip(zs, zs[1:]))):
            self.fail(el, "zplane z values must be monotonic")
        if zs[0] > zs[-1]:
            planes.reverse()
        sections = [(a, b) for a, b in zip(planes, planes[1:]) if b[0] > a[0] and max(a[2], b[2]) > 0]
        if not sections:
            self.fail(el, "the z planes enclose no volume")
        return planes, sections

    def _solid_polycone(self, el):
        lunit, aunit = self._units(el)
        planes, sections = self._zplanes(el, lunit)
        pieces = []
        for (z0, rmin0, rmax0), (z1, rmin1, rmax1) in sections:
            h = z1 - z0
            piece = Cone(rmax0, rmax1, h)
            inner = _inner_cone(rmin0, rmin1, h)
            if inner is not None:
                piece = piece - inner
            pieces.append(piece.translate((0.0, 0.0, 0.5 * (z0 + z1))))
        solid = pieces[0] if len(pieces) == 1 else Operation("union", pieces)
        rmax = max(p[2] for p in planes)
        zreach = max(abs(planes[0][0]), abs(planes[-1][0]))
        return _phi_cut(solid, *self._phi(el, aunit), rmax, zreach)

    def _solid_polyhedra(self, el):
        lunit, aunit = self._units(el)
        sides = self.number(el, "numsides")
        if sides != int(sides) or not 1 <= sides <= 10_000:
            self.fail(el, f"numsides: expected a whole number in 1..10000, got {sides:g}")
        sides = int(sides)
        phi0, dphi = self._phi(el, aunit)
        full = dphi >= TWO_PI - 1e-12
        step = dphi / sides
        if step >= math.pi - 1e-9:
            self.fail(el, f"each side spans {math.degrees(step):g} deg; a polyhedra side must span less than 180")
        planes, sections = self._zplanes(el, lunit)
        scale = max(max(p[2] for p in planes), max(abs(p[0]) for p in planes), 1e-9)
        per_chunk = sides if full else max(1, int(math.floor((math.pi - 1e-9) / step)))
        chunks = [range(k, min(k + per_chunk, sides)) for k in range(0, sides, per_chunk)]
        pieces = []
        for (z0, rmin0, rmax0), (z1, rmin1, rmax1) in sections:
            for chunk in chunks:
                outer = _frustum_chunk(phi0, step, chunk, full, z0, z1, rmax0, rmax1, 0.0, 0.0, 0.0)
                piece = outer
                if rmin0 > 0 or rmin1 > 0:
                    h = z1 - z0
                    s = (rmin1 - rmin0) / h
                    eb = 0.5 * h if s <= 0 else min(0.5 * h, rmin0 / s)
                    et = 0.5 * h if s >= 0 else min(0.5 * h, rmin1 / -s)
                    inner = _frustum_chunk(phi0, step, chunk, full, z0, z1, rmin0, rmin1, eb, et,
                                           1e-3 * scale)
                    piece = outer - inner
                pieces.append(piece)
        return pieces[0] if len(pieces) == 1 else Operation("union", pieces)

    def _solid_trd(self, el):
        lunit, _ = self._units(el)
        x1, x2, y1, y2 = (0.5 * self._nonnegative(el, a, lunit) for a in ("x1", "x2", "y1", "y2"))
        dz = 0.5 * self._positive(el, "z", lunit)
        verts = [(sx * x, sy * y, z) for z, x, y in ((-dz, x1, y1), (dz, x2, y2)) for sx in (-1, 1) for sy in (-1, 1)]
        return self._hull(el, verts)

    def _trap_vertices(self, dz, theta, phi, y1, x1, x2, alpha1, y2, x3, x4, alpha2):
        # G4Trap's vertex order and parameters (all half lengths).
        tx, ty = math.tan(theta) * math.cos(phi), math.tan(theta) * math.sin(phi)
        ta1, ta2 = math.tan(alpha1), math.tan(alpha2)
        return [(-dz * tx - y1 * ta1 - x1, -dz * ty - y1, -dz), (-dz * tx - y1 * ta1 + x1, -dz * ty - y1, -dz),
                (-dz * tx + y1 * ta1 - x2, -dz * ty + y1, -dz), (-dz * tx + y1 * ta1 + x2, -dz * ty + y1, -dz),
                (dz * tx - y2 * ta2 - x3, dz * ty - y2, dz), (dz * tx - y2 * ta2 + x3, dz * ty - y2, dz),
                (dz * tx + y2 * ta2 - x4, dz * ty + y2, dz), (dz * tx + y2 * ta2 + x4, dz * ty + y2, dz)]

    def _solid_trap(self, el):
        lunit, aunit = self._units(el)
        h = {a: 0.5 * self._nonnegative(el, a, lunit) for a in ("z", "y1", "x1", "x2", "y2", "x3", "x4")}
        ang = {a: self.number(el, a, 0.0, aunit) for a in ("theta", "phi", "alpha1", "alpha2")}
        return self._hull(el, self._trap_vertices(h["z"], ang["theta"], ang["phi"], h["y1"], h["x1"], h["x2"],
                                                  ang["alpha1"], h["y2"], h["x3"], h["x4"], ang["alpha2"]))

    def _solid_para(self, el):
        lunit, aunit = self._units(el)
        x, y, z = (0.5 * self._positive(el, a, lunit) for a in "xyz")
        alpha, theta, phi = (self.number(el, a, 0.0, aunit) for a in ("alpha", "theta", "phi"))
        return self._hull(el, self._trap_vertices(z, theta, phi, y, x, x, alpha, y, x, x, alpha))

    def _hull(self, el, vertices):
        v = np.array(vertices, dtype=np.float64)
        scale = max(float(np.max(np.abs(v))), 1e-300)
        tol = 1e-9 * scale
        centre = v.mean(axis=0)
        planes = []
        for i, j, k in itertools.combinations(range(len(v)), 3):
            n = np.cross(v[j] - v[i], v[k] - v[i])
            norm = np.linalg.norm(n)
            if norm <= 1e-12 * scale * scale:
                continue
            n = n / norm
            d = float(n @ v[i])
            if n @ centre > d:
                n, d = -n, -d
            if np.all(v @ n <= d + tol) and not any(np.allclose(q[:3], n, atol=1e-9, rtol=0) and
                                                    abs(q[3] - d) <= tol for q in planes):
                planes.append((*n, d))
        if len(planes) > 6:
            self.fail(el, "the faces are not planar (twisted); the parameters are inconsistent")
        if len(planes) < 4:
            self.fail(el, "the vertices do not enclose a solid")
        return ConvexPolyhedron(planes)

    def _solid_ellipsoid(self, el):
        lunit, _ = self._units(el)
        ax, by, cz = (self._positive(el, a, lunit) for a in ("ax", "by", "cz"))
        zcut1, zcut2 = self.number(el, "zcut1", 0.0, lunit), self.number(el, "zcut2", 0.0, lunit)
        # G4Ellipsoid: a cut of 0 means "no cut"; cuts beyond the surface are clamped.
        lo = -cz if zcut1 == 0 else max(-cz, zcut1)
        hi = cz if zcut2 == 0 else min(cz, zcut2)
        if lo >= hi:
            self.fail(el, f"zcut1 ({zcut1:g}) must be below zcut2 ({zcut2:g}) inside the ellipsoid")
        solid = Sphere(1.0).scale((ax, by, cz))
        if lo > -cz or hi < cz:
            solid = solid & Box((2.5 * ax, 2.5 * by, hi - lo)).translate((0.0, 0.0, 0.5 * (lo + hi)))
        return solid

    def _solid_eltube(self, el):
        lunit, _ = self._units(el)
        dx, dy, dz = (self._positive(el, a, lunit) for a in ("dx", "dy", "dz"))
        return Cylinder(1.0, 2.0 * dz).scale((dx, dy, 1.0))

    def _solid_elcone(self, el):
        lunit, _ = self._units(el)
        dx, dy = self._positive(el, "dx", 1.0), self._positive(el, "dy", 1.0)   # dimensionless slopes
        zmax = self._positive(el, "zmax", lunit)
        zcut = min(self._positive(el, "zcut", lunit), zmax)
        return Cone(zmax + zcut, zmax - zcut, 2.0 * zcut).scale((dx, dy, 1.0))

    def _operand(self, ref_el) -> Node | None:
        return self.solids[ref_el.get("ref")]

    def _boolean(self, el):
        first = self._operand(el.find("first"))
        second = self._operand(el.find("second"))
        if first is None or second is None:
            self._unsupported(el, "built from a skipped solid")
            return None
        t, r, _ = self.placement(el)
        second = second.transform(_affine(rotation_matrix(r), t))
        t1, r1, _ = self.placement(el, "first")
        if np.any(t1) or np.any(r1):
            first = first.transform(_affine(rotation_matrix(r1), t1))
        return Operation(_BOOLEANS[el.tag], (first, second))

    _solid_union = _solid_subtraction = _solid_intersection = _boolean

    def _solid_multiUnion(self, el):
        parts = []
        for node in el.findall("multiUnionNode"):
            solid = self._operand(node.find("solid"))
            if solid is None:
                self._unsupported(el, "built from a skipped solid")
                return None
            t, r, _ = self.placement(node)
            parts.append(solid.transform(_affine(rotation_matrix(r), t)))
        if not parts:
            self.fail(el, "needs at least one <multiUnionNode>")
        return Operation("union", parts)

    def _solid_scaledSolid(self, el):
        solid = self._operand(el.find("solidref"))
        if solid is None:
            self._unsupported(el, "built from a skipped solid")
            return None
        _, _, s = self.placement(el)
        if np.any(s == 0):
            self.fail(el, f"scale factors must be non-zero, got {s.tolist()}")
        return solid.scale(s)

    # ---- Structure ----
    def world_name(self) -> tuple[str, ET.Element]:
        setups = [s for s in self.root if s.tag == "setup"]
        if not setups:
            self.fail(self.root, "no <setup> with a <world ref=...>: the world volume is unknown")
        setup = next((s for s in setups if s.get("name") == "Default"), setups[0])
        world = setup.find("world")
        if world is None or not world.get("ref"):
            self.fail(setup, "needs <world ref=\"...\"/>")
        return world.get("ref"), world

    def _ref(self, el, tag) -> tuple[ET.Element, str]:
        child = el.find(tag)
        if child is None or not child.get("ref"):
            self.fail(el, f"needs <{tag} ref=\"...\"/>")
        return child, child.get("ref")

    def scene(self, depth: int | None, show_world: bool) -> Node:
        world, world_el = self.world_name()
        if world not in self.volumes:
            self.fail(world_el, f"refers to undefined volume {world!r}" +
                      (" (an assembly cannot be the world)" if world in self.assemblies else ""))
        placed: list[Node] = []
        count = 0
        # (element, world matrix, depth, ancestors) ; assemblies are expanded at the placing level
        stack = [(self.volumes[world], tf.IDENTITY, 0, (world,))]
        while stack:
            vol, matrix, level, ancestors = stack.pop()
            is_assembly = vol.tag == "assembly"
            if not is_assembly and (level > 0 or show_world):
                node = self._volume_solid(vol)
                if node is not None:
                    placed.append(node if matrix is tf.IDENTITY else node.transform(matrix))
            child_level = level if is_assembly else level + 1
            if depth is not None and child_level > depth:
                continue
            children = []
            for pv in vol:
                if pv.tag in ("replicavol", "paramvol", "divisionvol"):
                    self._unsupported(pv, f"<{pv.tag}> is not supported")
                    continue
                if pv.tag != "physvol":
                    continue
                if pv.find("file") is not None:
                    self._unsupported(pv, "<physvol> with <file> (an external GDML file) is not supported")
                    continue
                ref_el, ref = self._ref(pv, "volumeref")
                target = self.volumes.get(ref)
                if target is None:
                    target = self.assemblies.get(ref)
                if target is None:
                    self.fail(ref_el, f"refers to undefined volume {ref!r}")
                if ref in ancestors:
                    self.fail(pv, f"volume placement cycle: {' -> '.join(ancestors[ancestors.index(ref):] + (ref,))}")
                if len(ancestors) > MAX_VOLUME_DEPTH:
                    self.fail(pv, f"placements nested more than {MAX_VOLUME_DEPTH} deep")
                count += 1
                if count > MAX_PLACEMENTS:
                    self.fail(pv, f"more than {MAX_PLACEMENTS} placed volumes")
                t, r, s = self.placement(pv)
                if np.any(s == 0):
                    self.fail(pv, f"scale factors must be non-zero, got {s.tolist()}")
                # G4GDMLReadStructure::PhysvolRead: G4Transform3D(R.inverse(), t) * G4Scale3D(s).
                local = _affine(rotation_matrix(r).T @ np.diag(s), t)
                children.append((target, tf.compose(matrix, _frozen(local)), child_level, ancestors + (ref,)))
            stack.extend(reversed(children))   # popped in document order: a depth-first pre-order walk
        if not placed:
            raise FormatError(f"{self.source}: nothing to show: no placed volume "
                              f"{'at all' if show_world else 'below the world (show_world=True shows the world)'}")
        return placed[0] if len(placed) == 1 else Operation("union", placed)

    def _volume_solid(self, vol) -> Node | None:
        solid_el, solid_name = self._ref(vol, "solidref")
        node = self.solid(solid_name, solid_el)
        if node is None:
            return None
        mat = vol.find("materialref")
        if mat is not None and mat.get("ref"):
            name = _strip_pointer(mat.get("ref"))
            node = node.with_material(name)
        return node


def _frozen(m):
    m.setflags(write=False)
    return m


def _short(text: str, limit: int = 60) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _strip_pointer(name: str) -> str:
    """Geant4's writer appends '0x<address>' to names; its reader strips it, and so do we."""
    head = name.split("0x", 1)[0]
    return head if head else name


# ---- Geometry helpers ----

def _inner_cone(r_bottom: float, r_top: float, height: float) -> Node | None:
    """The hole r < r(z) of a frustum section |z| <= height/2, extended past both caps along its slope
    (as far as the radius stays >= 0) so that subtracting it leaves no coincident faces."""
    if r_bottom <= 0 and r_top <= 0:
        return None
    s = (r_top - r_bottom) / height
    eb = 0.5 * height if s <= 0 else min(0.5 * height, r_bottom / s)
    et = 0.5 * height if s >= 0 else min(0.5 * height, r_top / -s)
    rb, rt = max(0.0, r_bottom - s * eb), max(0.0, r_top + s * et)
    if rb == rt:
        return Cylinder(rb, height + eb + et).translate((0.0, 0.0, 0.5 * (et - eb)))
    return Cone(rb, rt, height + eb + et).translate((0.0, 0.0, 0.5 * (et - eb)))


def _wedge(phi0: float, dphi: float, radius: float, half_z: float) -> ConvexPolyhedron:
    """The convex wedge phi0 <= phi <= phi0 + dphi (dphi <= pi), |x|,|y| <= radius, |z| <= half_z."""
    phi1 = phi0 + dphi
    return ConvexPolyhedron([
        [math.sin(phi0), -math.cos(phi0), 0.0, 0.0], [-math.sin(phi1), math.cos(phi1), 0.0, 0.0],
        [1, 0, 0, radius], [-1, 0, 0, radius], [0, 1, 0, radius], [0, -1, 0, radius],
        [0, 0, 1, half_z], [0, 0, -1, half_z]])


def _phi_cut(solid: Node, phi0: float, dphi: float, radius: float, half_z: float) -> Node:
    """`solid` restricted to phi0 <= phi <= phi0 + dphi; the wedge overreaches the solid's extent."""
    if dphi >= TWO_PI - 1e-12:
        return solid
    r, h = 2.0 * radius + 1e-6, 2.0 * half_z + 1e-6
    if dphi <= math.pi:
        return solid & _wedge(phi0, dphi, r, h)
    return solid - _wedge(phi0 + dphi, TWO_PI - dphi, r, h)


def _theta_cut(solid: Node, theta0: float, theta1: float, reach: float) -> Node:
    """`solid` (centred on the origin, inside a ball of radius reach/2) limited to theta0 <= theta <= theta1."""
    half = 0.5 * math.pi

    def up(t):      # theta < t, z in [0, reach], apex at the origin
        return Cone(0.0, reach * math.tan(t), reach).translate((0.0, 0.0, 0.5 * reach))

    def down(t):    # theta > pi - t, z in [-reach, 0]
        return Cone(reach * math.tan(t), 0.0, reach).translate((0.0, 0.0, -0.5 * reach))

    def half_space(sign):
        return Box((2 * reach, 2 * reach, reach)).translate((0.0, 0.0, 0.5 * sign * reach))

    if theta0 > 1e-12:
        if abs(theta0 - half) < 1e-9:
            solid = solid & half_space(-1)
        elif theta0 < half:
            solid = solid - up(theta0)
        else:
            solid = solid & down(math.pi - theta0)
    if theta1 < math.pi - 1e-12:
        if abs(theta1 - half) < 1e-9:
            solid = solid & half_space(+1)
        elif theta1 > half:
            solid = solid - down(math.pi - theta1)
        else:
            solid = solid & up(theta1)
    return solid


def _frustum_chunk(phi0, step, chunk, full, z0, z1, r0, r1, extend_bottom, extend_top, phi_margin):
    """Sides `chunk` of a polyhedra section between z0 (apothem r0) and z1 (apothem r1), as one convex
    polyhedron; a partial chunk is closed by radial planes (pushed out by phi_margin), the caps are pushed
    out by extend_bottom/extend_top."""
    s = (r1 - r0) / (z1 - z0)
    planes = []
    for k in chunk:
        a = phi0 + (k + 0.5) * step
        planes.append([math.cos(a), math.sin(a), -s, r0 - s * z0])
    if not full:
        b0, b1 = phi0 + chunk[0] * step, phi0 + (chunk[-1] + 1) * step
        planes.append([math.sin(b0), -math.cos(b0), 0.0, phi_margin])
        planes.append([-math.sin(b1), math.cos(b1), 0.0, phi_margin])
    planes.append([0.0, 0.0, 1.0, z1 + extend_top])
    planes.append([0.0, 0.0, -1.0, -(z0 - extend_bottom)])
    return ConvexPolyhedron(planes)


# ---- Entry points ----

_OPTIONS = ("solid", "depth", "show_world", "on_unsupported")


def _check_options(depth, on_unsupported, source):
    if on_unsupported not in ("error", "skip"):
        raise FormatError(f"{source}: on_unsupported must be 'error' or 'skip', got {on_unsupported!r}")
    if depth is not None and (isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) or depth < 0):
        raise FormatError(f"{source}: depth must be None or an integer >= 0, got {depth!r}")


def loads(text, source: str = "<string>", *, base_dir: str | None = None, solid: str | None = None,
          depth: int | None = None, show_world: bool = False, on_unsupported: str = "error") -> Node:
    """Read a GDML document from a string or bytes; see the module docstring. Lengths in mm."""
    _check_options(depth, on_unsupported, source)
    data = text.encode("utf-8") if isinstance(text, str) else bytes(text)
    if len(data) > MAX_FILE_BYTES:
        raise FormatError(f"{source}: larger than {MAX_FILE_BYTES} bytes")
    root, lines = _parse_xml(data, source, base_dir)
    reader = _Reader(root, lines, source, on_unsupported)
    if solid is not None:
        if solid not in reader.solid_elements:
            raise FormatError(f"{source}: no solid named {solid!r}" +
                              (f"; solids: {', '.join(list(reader.solid_elements)[:20])}"
                               if reader.solid_elements else "; the document defines no solids"))
        node = reader.solid(solid, root)
        if node is None:
            raise FormatError(f"{source}: solid {solid!r} is not supported and was skipped")
        return node
    return reader.scene(depth, show_world)


def load(path, *, solid: str | None = None, depth: int | None = None, show_world: bool = False,
         on_unsupported: str = "error") -> Node:
    """Read a GDML file: the placed scene (world hidden), or with `solid=` one solid in its own frame.

    Lengths are in mm. `depth` keeps placed volumes at most that many levels below the world;
    `on_unsupported` is "error" (FormatError) or "skip" (warn and leave the solid out).
    """
    path = os.fspath(path)
    data, _ = read_model_bytes(path, MAX_FILE_BYTES)
    source = os.path.basename(path) or path
    return loads(data, source, base_dir=os.path.dirname(os.path.abspath(path)), solid=solid, depth=depth,
                 show_world=show_world, on_unsupported=on_unsupported)
