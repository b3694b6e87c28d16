"""One GDML document being read: its sections, messages that name the element and line,
and attribute values (expressions times units).
"""
from __future__ import annotations

import math
import warnings
import xml.etree.ElementTree as ET

from ..reading import FormatError
from .defines import read_defines
from .expressions import Expressions, short
from .loops import expand_loops

# Geant4's simple-extension schema (examples G03, CaTS) wraps GDML in another root element
# and adds an <extension> section of named colours, referenced by <colorref> in volumes.
ROOTS = ("gdml", "gdml_simple_extension")


class Document:
    """The parsed tree of a GDML file with its tables of named defines, solids and volumes."""

    def __init__(self, root, lines, source: str, on_unsupported: str):
        self.root, self.lines, self.source = root, lines, source
        self.skip_unsupported = on_unsupported == "skip"
        self.expressions = Expressions()
        self.vectors: dict[str, dict[str, ET.Element]] = {"position": {}, "rotation": {}, "scale": {}}
        self.solid_elements: dict[str, ET.Element] = {}
        self.volumes: dict[str, ET.Element] = {}
        self.assemblies: dict[str, ET.Element] = {}
        self.variables: set[str] = set()          # names of <variable>s: only they may be loop variables
        self.colours: dict[str, tuple[float, ...]] = {}   # <extension> colours: name -> (R, G, B, A)
        self.warned: set[str] = set()
        if root.tag not in ROOTS:
            raise FormatError(f"{source}: line {lines.get(id(root), 1)}: the root element is <{root.tag}>, "
                              f"expected <gdml>")
        for section in root:
            if section.tag in ("define", "solids", "structure"):
                expand_loops(self, section)
            if section.tag == "define":
                read_defines(self, section)
            elif section.tag == "solids":
                for el in section:
                    self.register(self.solid_elements, el, "solid")
            elif section.tag == "structure":
                for el in section:
                    if el.tag == "volume":
                        self.register(self.volumes, el, "volume")
                    elif el.tag == "assembly":
                        self.register(self.assemblies, el, "assembly")
                    elif el.tag in ("skinsurface", "bordersurface"):
                        pass
                    else:
                        self.fail(el, f"unknown structure element <{el.tag}>")
            elif section.tag == "extension":
                self._read_colours(section)
            elif section.tag in ("materials", "setup", "userinfo"):
                pass
            else:
                self.fail(section, f"unknown section <{section.tag}>; expected define, materials, solids, "
                                   f"structure, setup")
        for name in self.volumes.keys() & self.assemblies.keys():
            self.fail(self.assemblies[name], f"the name {name!r} is used by a volume and an assembly")

    def _read_colours(self, section):
        for el in section:
            if el.tag != "color":
                continue
            if not el.get("name"):
                self.fail(el, "a color needs a name attribute")
            rgba = tuple(self.number(el, c, 1.0 if c == "A" else None) for c in "RGBA")
            if not all(0.0 <= c <= 1.0 for c in rgba):
                self.fail(el, f"colour components must lie in [0, 1], got {list(rgba)}")
            self.colours[el.get("name")] = rgba

    def where(self, el) -> str:
        line = self.lines.get(id(el))
        name = el.get("name")
        tag = f'<{short(el.tag, 40)} name="{short(name)}">' if name is not None else f"<{short(el.tag, 40)}>"
        return f"{self.source}: line {line}: {tag}" if line else f"{self.source}: {tag}"

    def fail(self, el, message: str):
        raise FormatError(f"{self.where(el)}: {message}")

    def unsupported(self, el, message: str):
        if not self.skip_unsupported:
            raise FormatError(f"{self.where(el)}: {message} (on_unsupported='skip' leaves it out)")
        self.warn(el, message + "; skipped")

    def warn(self, el, message: str):
        """A UserWarning naming the element, once per message."""
        text = f"{self.where(el)}: {message}"
        if text not in self.warned:
            self.warned.add(text)
            warnings.warn(text, UserWarning, stacklevel=4)

    def register(self, table, el, what):
        name = el.get("name")
        if not name:
            self.fail(el, f"a {what} needs a name attribute")
        if name in table:
            self.fail(el, f"{what} {name!r} is defined twice (first at line {self.lines.get(id(table[name]))})")
        table[name] = el

    # ---- Attribute values ----
    def number(self, el, attr, default=None, unit: float = 1.0) -> float:
        text = el.get(attr)
        if text is None:
            if default is None:
                self.fail(el, f"missing attribute {attr!r}")
            return float(default)
        try:
            value = self.expressions.evaluate(text) * unit
        except FormatError as e:
            self.fail(el, f'{attr}="{short(text)}": {e}')
        if not math.isfinite(value):
            self.fail(el, f'{attr}="{short(text)}": the value is not finite')
        return value

    def unit(self, el, attr, default: str) -> float:
        text = el.get(attr, default)
        try:
            value = self.expressions.evaluate(text)
        except FormatError as e:
            self.fail(el, f'{attr}="{short(text)}": {e}')
        if not math.isfinite(value) or value == 0:
            self.fail(el, f'{attr}="{short(text)}": not a usable unit')
        return value
