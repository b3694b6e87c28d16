"""Syntax: `.csg` text -> a tree of statements (`modifiers name(args) { children }`), with
explicit stacks and bounded counts."""
from __future__ import annotations

from . import limits
from .lexer import EOF, KEYWORDS, describe_token, tokens
from .source import Source


class Range:
    __slots__ = ("values",)

    def __init__(self, values):
        self.values = values


class Statement:
    """`modifiers name(args) { children }`; name None for a bare `{ ... }` block."""

    __slots__ = ("name", "args", "pos", "modifiers", "children")

    def __init__(self, name, args, pos, modifiers):
        self.name, self.args, self.pos, self.modifiers, self.children = name, args, pos, modifiers, []


class TokenWindow:
    """The token stream indexed like a list, read lazily and forgetting what the parser has
    passed: a file of many tokens costs memory for a few, not for all of them."""

    __slots__ = ("stream", "buffer", "offset", "last")

    def __init__(self, stream):
        self.stream, self.buffer, self.offset, self.last = stream, [], 0, None

    def __getitem__(self, i: int):
        k = i - self.offset
        if k >= 4096:                     # the parser never looks back: drop what it passed
            del self.buffer[:k]
            self.offset, k = i, 0
        while k >= len(self.buffer):
            tok = next(self.stream, None)
            if tok is None:
                tok = self.last           # past the end, the end-of-file token repeats
            self.last = tok
            self.buffer.append(tok)
        return self.buffer[k]


class Parser:
    def __init__(self, src: Source):
        self.src = src
        self.toks = TokenWindow(tokens(src))
        self.i = 0
        self.count = 0

    def peek(self):
        return self.toks[self.i]

    def expect(self, kind: str, what: str):
        tok = self.toks[self.i]
        if tok[0] != kind:
            self.src.fail(tok[2], f"expected {what}, got {describe_token(tok)}")
        self.i += 1
        return tok

    # -- values --
    def value(self, depth: int = 0):
        tok = self.toks[self.i]
        kind, val, pos = tok
        if kind in ("-", "+"):
            # Signs in a row are read in a loop (a thousand of them nested Python calls).
            negative = False
            while self.toks[self.i][0] in ("-", "+"):
                negative ^= self.toks[self.i][0] == "-"
                self.i += 1
            v = self.value(depth)
            if isinstance(v, bool) or not isinstance(v, float):
                self.src.fail(pos, f"unary {kind} needs a number, got {'a vector' if isinstance(v, list) else repr(v)}")
            return -v if negative else v
        self.i += 1
        if kind == "num" or kind == "str":
            return val
        if kind == "id":
            if val in KEYWORDS:
                return KEYWORDS[val]
            self.src.fail(pos, f"unknown name {val!r} in a value (a .csg file holds only literal values)")
        if kind == "[":
            if depth >= limits.MAX_VALUE_DEPTH:
                self.src.fail(pos, f"vectors nested more than {limits.MAX_VALUE_DEPTH} deep")
            items = []
            if self.toks[self.i][0] == "]":
                self.i += 1
                return items
            items.append(self.value(depth + 1))
            if self.toks[self.i][0] == ":":           # a range [start : step : end]
                while self.toks[self.i][0] == ":" and len(items) < 3:
                    self.i += 1
                    items.append(self.value(depth + 1))
                self.expect("]", "']' closing a range")
                return Range(items)
            while True:
                tok = self.toks[self.i]
                self.i += 1
                if tok[0] == "]":
                    return items
                if tok[0] != ",":
                    self.src.fail(tok[2], f"expected ',' or ']' in a vector, got {describe_token(tok)}")
                if self.toks[self.i][0] == "]":     # trailing comma
                    self.i += 1
                    return items
                items.append(self.value(depth + 1))
        self.src.fail(pos, f"expected a value, got {describe_token(tok)}")

    def args(self):
        args = []
        self.expect("(", "'('")
        if self.toks[self.i][0] == ")":
            self.i += 1
            return args
        while True:
            kind, val, pos = self.toks[self.i]
            if kind == "id" and self.toks[self.i + 1][0] == "=":
                self.i += 2
                args.append((val, self.value(), pos))
            else:
                args.append((None, self.value(), pos))
            tok = self.toks[self.i]
            self.i += 1
            if tok[0] == ")":
                return args
            if tok[0] != ",":
                self.src.fail(tok[2], f"expected ',' or ')' after an argument, got {describe_token(tok)}")

    # -- statements (explicit stack: files may nest deeply) --
    def parse(self) -> Statement:
        root = Statement(None, [], 0, "")
        stack = [(root, "root")]      # (statement, 'root' | 'block' | 'single')
        while True:
            top, mode = stack[-1]
            if mode == "single" and top.children:
                stack.pop()
                continue
            kind, val, pos = self.toks[self.i]
            if kind == "}":
                if mode != "block":
                    self.src.fail(pos, "unexpected '}' (no block open)")
                self.i += 1
                stack.pop()
                continue
            if kind == EOF:
                if mode == "root":
                    return root
                self.src.fail(pos, f"unexpected end of file: the block of "
                                   f"{top.name or 'a { block'} at {self.src.where(top.pos)} is not closed")
            modifiers = ""
            while kind in ("#", "%", "!", "*"):
                if kind not in modifiers:          # each modifier counts once, however often repeated
                    modifiers += kind
                self.i += 1
                kind, val, pos = self.toks[self.i]
            # Empty statements count too, so that a file of nothing but ';' is bounded in time.
            self.count += 1
            if self.count > limits.MAX_STATEMENTS:
                self.src.fail(pos, f"more than {limits.MAX_STATEMENTS} statements")
            if kind == ";":
                self.i += 1
                if mode == "single":
                    stack.pop()
                continue
            if len(stack) > limits.MAX_DEPTH:
                self.src.fail(pos, f"statements nested more than {limits.MAX_DEPTH} deep")
            if kind == "{":
                self.i += 1
                st = Statement(None, [], pos, modifiers)
                top.children.append(st)
                stack.append((st, "block"))
                continue
            if kind != "id":
                self.src.fail(pos, f"expected a statement (a node name such as cube or group), got "
                                   f"{describe_token(self.toks[self.i])}")
            if val in KEYWORDS:
                self.src.fail(pos, f"expected a node name, got the keyword {val!r}")
            self.i += 1
            st = Statement(val, self.args(), pos, modifiers)
            top.children.append(st)
            kind = self.toks[self.i][0]
            if kind == ";":
                self.i += 1
            elif kind == "{":
                self.i += 1
                stack.append((st, "block"))
            else:
                stack.append((st, "single"))
