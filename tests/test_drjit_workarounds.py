"""The Dr.Jit 1.5 patterns the kernel avoids, and the kernel property they would break.

The kernel (`engine/automaton.py`) keeps three habits from Dr.Jit 1.5.0 trouble seen while it
was written: per-lane stack indices start full width (`dr.zeros(UInt32, n)`, not a width-1
`UInt32(0)`: every lane used the largest lane's index), `dr.alloc_local` entries are written
by the kernel rather than with `value=` (16+ entries aborted LLVM compilation), and register
updates use `dr.select` rather than a literal assigned in two sibling branches of a symbolic
`if`. The first three tests run each avoided pattern alone, in a subprocess (a crash must not
end the test run): on Dr.Jit 1.5.0 here they pass in isolation, so they are canaries that
tell when a Dr.Jit update breaks them. The last test checks what the bugs broke in the
kernel: every lane of a wide batch gets the answer of the float64 reference, and the same
answer as the ray traced alone.
"""
from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import mitsuba_csg as csg
from agreement import compare
from strategies import make_rays, models

pytestmark = pytest.mark.usefixtures("jit_variant")

PRELUDE = """
import numpy as np
import mitsuba_csg  # LLVM 19 and the variant, as the kernel gets them
import drjit as dr
from drjit.llvm import Float, UInt32
"""


def run_pattern(body: str, tmp_path) -> str:
    script = tmp_path / "pattern.py"          # @dr.syntax needs the source in a file
    script.write_text(PRELUDE + textwrap.dedent(body))
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    return run.stdout.strip()


def test_stack_index_from_a_width_one_literal(tmp_path):
    out = run_pattern("""
        @dr.syntax
        def push_pop(n):
            stack = dr.alloc_local(UInt32, 4)
            lane = dr.arange(UInt32, n)
            depth = lane % 3 + 1                 # lanes push different numbers of entries
            sp = UInt32(0)                       # the pattern: a width-1 literal index
            while sp < depth:
                stack.write(lane * 10 + sp, sp)
                sp += 1
            total = dr.zeros(UInt32, n)
            while sp > 0:
                sp -= 1
                total += stack.read(sp)
            return total
        for n in (1, 64):
            lane = np.arange(n)
            expected = [sum(l * 10 + s for s in range(l % 3 + 1)) for l in lane]
            print(np.array_equal(push_pop(n).numpy(), expected))
    """, tmp_path)
    assert out.split() == ["True", "True"]


def test_alloc_local_with_value_and_many_entries(tmp_path):
    out = run_pattern("""
        @dr.syntax
        def read_all(n, size):
            s = dr.alloc_local(Float, size, value=dr.zeros(Float, n))
            i = dr.zeros(UInt32, n)
            acc = dr.zeros(Float, n)
            while i < size:
                acc += s.read(i) + 1.0
                i += 1
            return acc
        print(all(np.all(read_all(64, size).numpy() == size) for size in (8, 16, 32)))
    """, tmp_path)
    assert out == "True"


def test_literal_assigned_in_sibling_branches(tmp_path):
    out = run_pattern("""
        @dr.syntax
        def branches(n):
            lane = dr.arange(UInt32, n)
            state = dr.zeros(UInt32, n)
            steps = dr.zeros(UInt32, n)
            while steps < 3:
                if lane % 3 == 0:
                    state = UInt32(5)
                elif lane % 3 == 1:
                    state = UInt32(7)
                steps += 1
            return state
        print(np.array_equal(branches(64).numpy(), np.array([5, 7, 0] * 22)[:64]))
    """, tmp_path)
    assert out == "True"


@given(model=models(max_leaves=6), seed=st.integers(0, 2**31))
def test_lanes_are_independent(model, seed):
    """Each lane of a 64-wide batch agrees with the reference and with its ray traced alone."""
    o, d = make_rays(seed, 64, targets=[leaf.matrix[:3, 3] for leaf in model.leaves()])
    prepared = csg.prepare(model)
    wide = csg.trace(prepared, o, d)
    compare(model, wide, o, d)
    for i in range(0, 64, 9):
        single = csg.trace(prepared, o[i:i + 1], d[i:i + 1])
        assert single.t[0] == wide.t[i] or (np.isnan(single.t[0]) and np.isnan(wide.t[i]))
        assert single.prim[0] == wide.prim[i]


def test_rays_sharing_one_origin_are_independent_lanes():
    """A camera's rays share one origin, a width-1 array: the kernel's registers must still be
    full width. (They took the origin's width, and Dr.Jit 1.5's LLVM backend then mixed the
    lanes' per-lane stacks: about 1 % of a Cheese's rays near hole rims hit the wrong surface,
    and which ones depended on which other lanes were active.)"""
    from mitsuba_csg.queries import rays_to_device, trace_rays
    from mitsuba_csg.scenes import cheese
    prepared = csg.prepare(cheese(20, seed=3))
    b = prepared.tree.b
    camera = np.array([4.0, -6.0, 3.0])
    u, v = np.meshgrid(np.linspace(-1.3, 1.3, 160), np.linspace(-1.3, 1.3, 120))
    targets = np.column_stack([u.ravel(), v.ravel(), 0.3 * u.ravel() - 0.2 * v.ravel()])
    d = targets - camera
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n = len(d)
    alone = trace_rays(prepared, rays_to_device(np.tile(camera, (n, 1)), b), rays_to_device(d, b))
    shared = b.Array3f(*[b.Float(float(c)) for c in camera])          # width 1
    rng = np.random.default_rng(0)
    for active in (np.ones(n, bool), rng.random(n) < 0.5, rng.random(n) < 0.1):
        hits = trace_rays(prepared, shared, rays_to_device(d, b), active=b.Bool(active))
        np.testing.assert_array_equal(np.asarray(hits.t)[active], np.asarray(alone.t)[active])
        np.testing.assert_array_equal(np.asarray(hits.prim)[active], np.asarray(alone.prim)[active])
