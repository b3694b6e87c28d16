"""GDML's `<loop for="i" from="1" to="n" step="1">`: its contents repeated, as Geant4 reads them.

Geant4 (`G4GDMLRead::LoopRead`) sets the loop variable, which must be a defined `<variable>`,
and reads the loop's contents once per value while `value <= to` (so a loop that counts down
runs at most once); without `from` it starts at the variable's current value. Inside a loop,
names and references are passed through `SolveBrackets`: `Box[i][j]` names `Box_<i-1>_<j-1>`.
We expand each loop in place before its section is read: the copies get their names solved
and every attribute that mentions a loop variable evaluated with the variable's value of
that pass, so what is read later does not depend on when it is read. After the loop the
variable has its value from before the loop again.
"""
from __future__ import annotations

import ast
import copy

from ..reading import FormatError
from .expressions import _LEADING_ZEROS, short

MAX_LOOP_ELEMENTS = 200_000        # elements made by all loops of a document
_NAME_ATTRIBUTES = ("name", "ref")


# Where Geant4 reads loops: in a section, and in a volume or assembly (loops of placements).
_HOLDERS = ("volume", "assembly")


def expand_loops(doc, section) -> None:
    """Replace every `<loop>` of a section (and of its volumes) by the copies of its contents."""
    expander = _Expander(doc)
    try:
        expander.expand_children(section, ())
    except RecursionError:
        doc.fail(section, "elements inside a <loop> are nested too deeply")


class _Expander:
    def __init__(self, doc):
        self.doc = doc
        self.made = 0

    def expand_children(self, parent, active: tuple[str, ...]):
        if not any(child.tag == "loop" or child.tag in _HOLDERS for child in parent):
            return
        children = []
        for child in list(parent):
            if child.tag == "loop":
                children.extend(self.run(child, active))
            else:
                if child.tag in _HOLDERS:
                    self.expand_children(child, active)
                children.append(child)
        parent[:] = children

    def run(self, loop, active):
        doc = self.doc
        scalars = doc.expressions.scalars
        var = loop.get("for")
        if not var:
            doc.fail(loop, "needs a for attribute naming the loop variable")
        if var not in doc.variables:
            doc.fail(loop, f"for={var!r}: the loop variable must be a <variable> defined before the loop")
        if var in active:
            doc.fail(loop, f"for={var!r}: the variable of an enclosing loop")
        try:
            start = doc.expressions.integer(loop.get("from")) if loop.get("from") is not None else \
                doc.expressions.integer(var)
            stop = doc.expressions.integer(loop.get("to", ""))
            step = doc.expressions.integer(loop.get("step", ""))
        except FormatError as e:
            doc.fail(loop, str(e))
        if step == 0 or (start < stop and step < 0):
            doc.fail(loop, f"step {step} never reaches to={stop} from {start}: an endless loop")
        if start > stop and step > 0:        # Geant4 refuses this too
            doc.fail(loop, f"from {start} lies past to={stop} with a positive step")
        # Refused before the copies are made, when the count is known up front.
        trips = max(0, (stop - start) // step + 1)
        body = sum(1 for child in loop for _ in child.iter())
        if self.made + trips * body > MAX_LOOP_ELEMENTS:
            doc.fail(loop, f"loops make more than {MAX_LOOP_ELEMENTS} elements ({trips} passes of {body})")
        saved = scalars[var]
        out = []
        inner = active + (var,)
        value = start
        try:
            while value <= stop:
                scalars[var] = float(value)
                for child in loop:
                    if child.tag == "loop":
                        out.extend(self.run(child, inner))
                        continue
                    clone = self.bind(child, inner)
                    self.expand_children(clone, inner)
                    out.append(clone)
                value += step
        finally:
            scalars[var] = saved
        return out

    def bind(self, el, active):
        """A copy of `el` with names solved and loop variables replaced by their values;
        nested loops are copied as they are (they bind their own contents when they run)."""
        self.made += 1
        if self.made > MAX_LOOP_ELEMENTS:
            self.doc.fail(el, f"loops make more than {MAX_LOOP_ELEMENTS} elements")
        clone = copy.copy(el)
        clone.attrib = {key: self.value(el, key, text, active) for key, text in el.attrib.items()}
        if el.tag == "loop":
            clone[:] = list(el)
        else:
            if el.tag == "expression" and el.text and _mentions(el.text, active):
                clone.text = self.evaluated(el, "text", el.text)
            clone[:] = [self.bind(child, active) for child in el]
        self.doc.lines[id(clone)] = self.doc.lines.get(id(el))
        return clone

    def value(self, el, key, text, active):
        if key in _NAME_ATTRIBUTES:
            try:
                return self.doc.expressions.solve_brackets(text)
            except FormatError as e:
                self.doc.fail(el, f'{key}="{short(text)}": {e}')
        if key == "for" or not _mentions(text, active):
            return text
        return self.evaluated(el, key, text)

    def evaluated(self, el, key, text):
        try:
            return repr(self.doc.expressions.evaluate(text))
        except FormatError as e:
            self.doc.fail(el, f'{key}="{short(text)}": {e}')


def _mentions(text: str, names) -> bool:
    """Whether the expression `text` uses one of `names` (False for text that is no expression)."""
    if not any(name in text for name in names):
        return False
    try:
        tree = ast.parse(_LEADING_ZEROS.sub("", text).replace("^", "**").replace("[", "(").replace("]", ")"),
                         mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return False
    return any(isinstance(node, ast.Name) and node.id in names for node in ast.walk(tree))
