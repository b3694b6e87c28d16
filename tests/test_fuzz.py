"""Fuzzing every format end to end: mutated copies of valid files (native JSON, GDML, OpenSCAD
.csg, STL) either fail with the package's error naming the file, or load into a model that
traces without NaN. A few hundred cases in the normal suite, thousands under `slow`; each
case has a time limit, so a hang fails the test instead of stalling it."""
from __future__ import annotations

import random
import re
import signal
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

import mitsuba_csg as csg

ROOT = Path(__file__).resolve().parents[1]
GDML_SEEDS = ["one-box.gdml", "two-boxes.gdml", "intersection-boxes.gdml", "simpleCone.gdml", "multiUnion.gdml",
              "transformed-box.gdml", "replicated.gdml", "divisionvol.gdml", "tess.gdml", "loop.gdml"]
CSG_SEED = """group() {
  multmatrix([[1, 0, 0, -24], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) {
    difference() { cube(size = [15, 15, 15], center = true); sphere($fn = 0, $fa = 12, $fs = 2, r = 10); }
  }
  intersection() { cube(size = 15, center = true); cylinder(h = 10, r1 = 5, r2 = 0, center = false); }
  polyhedron(points = [[10, 0, 0], [0, 10, 0], [-10, 0, 0], [0, -10, 0], [0, 0, 10]],
             faces = [[0, 1, 2, 3], [4, 1, 0], [4, 2, 1], [4, 3, 2], [4, 0, 3]], convexity = 1);
  linear_extrude(height = 4, twist = 30, slices = 3) square(size = [3, 2]);
}
"""
STL_SEED = "solid cube\n" + "".join(
    f"facet normal 0 0 0\nouter loop\nvertex {a}\nvertex {b}\nvertex {c}\nendloop\nendfacet\n"
    for a, b, c in [("0 0 0", "0 1 0", "1 1 0"), ("0 0 0", "1 1 0", "1 0 0"), ("0 0 1", "1 0 1", "1 1 1"),
                    ("0 0 1", "1 1 1", "0 1 1"), ("0 0 0", "1 0 0", "1 0 1"), ("0 0 0", "1 0 1", "0 0 1"),
                    ("0 1 0", "0 1 1", "1 1 1"), ("0 1 0", "1 1 1", "1 1 0"), ("0 0 0", "0 0 1", "0 1 1"),
                    ("0 0 0", "0 1 1", "0 1 0"), ("1 0 0", "1 1 0", "1 1 1"), ("1 0 0", "1 1 1", "1 0 1")]) \
    + "endsolid cube\n"
NUMBERS = ["0", "-0", "-1", "1e308", "-1e308", "1e-320", "5e-324", "1e30", "1e-30", "nan", "NaN", "inf", "-inf",
           "Infinity", "1" * 60, "2.5", "1e999", "0.0001", "123456789", "3"]
JUNK = ["", "<", ">", "/", "=", '"', "{", "}", "[", "]", "(", ")", ";", ",", ":", "#", "&", "&amp;", "\x00", "é",
        "<!--", "]]>", " ", "\n", "union", "sphere", "cube(1);", "ref", "name", "children", "type"]


def seeds() -> list[tuple[str, str]]:
    out = [("json", (ROOT / "scenes" / "models" / "demo_cheese_small.json").read_text()),
           ("csg", CSG_SEED), ("stl", STL_SEED)]
    out += [("gdml", (ROOT / "tests" / "data" / "gdml" / name).read_text()) for name in GDML_SEEDS]
    return out


def mutate(text: str, rng: random.Random) -> str:
    for _ in range(rng.choice([1, 1, 1, 2, 3])):
        op = rng.choice([0, 0, 0, 1, 2, 3, 4, 5])            # mostly numbers: those keep the syntax
        i = rng.randrange(len(text) + 1)
        if op == 0:                                        # a number becomes an extreme one
            numbers = list(re.finditer(r"-?[0-9][0-9.]*(?:[eE][-+]?[0-9]+)?", text))
            if numbers:
                m = rng.choice(numbers)
                text = text[:m.start()] + rng.choice(NUMBERS) + text[m.end():]
        elif op == 1:
            text = text[:i] + text[i + rng.randint(1, 12):]           # delete a span
        elif op == 2:
            text = text[:i] + rng.choice(JUNK + NUMBERS) + text[i:]   # insert a token
        elif op == 3:
            j = min(len(text), i + rng.randint(1, 80))                # duplicate a span
            text = text[:j] + text[i:j] + text[j:]
        elif op == 4 and rng.random() < 0.3:
            text = text[:i]                                           # truncate
        elif text:
            b = bytearray(text.encode("utf-8", "surrogateescape"))    # flip a byte
            b[rng.randrange(len(b))] = rng.randrange(256)
            text = b.decode("utf-8", "replace")
    return text


class Hang(Exception):
    pass


@contextmanager
def time_limit(seconds: int):
    def fire(*_):
        raise Hang(f"no answer within {seconds} s")
    previous = signal.signal(signal.SIGALRM, fire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def check_case(kind: str, text: str, path: Path) -> str:
    path = path.with_suffix("." + kind)
    path.write_text(text, encoding="utf-8", errors="surrogateescape")
    try:
        with time_limit(60), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = csg.load(str(path))
            lower, upper = model.bounds()
            rng = np.random.default_rng(0)
            centre, size = (lower + upper) / 2, np.max(upper - lower)
            targets = centre + rng.uniform(-0.5, 0.5, (64, 3)) * (upper - lower)
            origins = centre + rng.normal(size=(64, 3)) * 3 * size
            hits = csg.trace(model, origins, targets - origins, max_iterations=100_000)
    except csg.CSGError as e:
        assert path.name in str(e) or kind == "json" and str(e).startswith(str(path)) \
            or "primitive" in str(e) or "needs about" in str(e), f"the error does not name the file: {e}"
        return "error"
    except Hang:
        raise AssertionError(f"{kind} input hung:\n{text[:3000]}") from None
    except Exception as e:
        raise AssertionError(f"{type(e).__name__}: {e}\n--- {kind} input ---\n{text[:3000]}") from e
    finished = ~np.isnan(hits.t)
    assert np.all(np.isfinite(hits.t[finished]) | np.isinf(hits.t[finished])), "NaN t"
    hit = np.isfinite(hits.t)
    assert np.all(np.isfinite(hits.normal[hit])), f"NaN normals for\n{text[:3000]}"
    return "traced"


def run_fuzz(cases: int, seed: int, tmp_path: Path):
    rng = random.Random(seed)
    pool = seeds()
    outcomes = {"error": 0, "traced": 0}
    for k in range(cases):
        kind, text = pool[k % len(pool)]
        outcomes[check_case(kind, mutate(text, rng), tmp_path / f"case{k % 7}")] += 1
    return outcomes


def test_fuzz_every_format_end_to_end(tmp_path):
    outcomes = run_fuzz(300, 2026, tmp_path)
    assert outcomes["error"] > 30 and outcomes["traced"] > 30, outcomes


@pytest.mark.slow
def test_fuzz_every_format_end_to_end_thoroughly(tmp_path):
    outcomes = run_fuzz(3000, 12, tmp_path)
    assert outcomes["error"] > 300 and outcomes["traced"] > 300, outcomes
