"""GDML's XML with a DOCTYPE policy: expat, internal entities without nesting and bounded in
size, external entities only from local files beside the document, bounded element and
text counts. Returns the element tree and the line of every element for messages.
"""
from __future__ import annotations

import os
import re
import stat
import xml.etree.ElementTree as ET
import xml.parsers.expat as expat

from ..reading import FormatError

MAX_FILE_BYTES = 1 << 30           # one document (external entities included)
MAX_ELEMENTS = 5_000_000           # XML elements, after entity expansion
MAX_TEXT_CHARS = 50_000_000        # character data, after entity expansion
MAX_ENTITY_CHARS = 1 << 16         # replacement text of one internal entity
MAX_EXTERNAL_ENTITIES = 256        # external entity references in one document
MAX_ENTITY_NESTING = 8             # external entities referenced from external entities


class _ParseAbort(Exception):
    """Raised inside expat handlers; turned into a FormatError with the line."""


def parse_xml(data: bytes, source: str, base_dir: str | None):
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
            if not stat.S_ISREG(os.stat(path).st_mode):
                raise _ParseAbort(f"external entity {name!r} ({system_id!r}) is not a regular file (a FIFO, "
                                  f"device, socket or directory), so it is not read")
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
