"""The native `.json` model format (`mitsuba_csg.formats.native_json`): exact round trips, every error with
its JSON path, deep and large documents without RecursionError, and a fuzz test of mutated files."""
from __future__ import annotations

import copy
import json
import math
import random
import re
from pathlib import Path

import manifold3d
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mitsuba_csg.formats import native_json as native
from mitsuba_csg.errors import ModelError
from mitsuba_csg.model import Node, Operation, difference, union
from mitsuba_csg.formats.native_json import FormatError, from_dict, load, load_with_materials, save, to_dict
from mitsuba_csg.model.mesh import Mesh
from mitsuba_csg.model.primitives import Box, Cone, ConvexPolyhedron, Cylinder, Prism, Sphere, Torus
from strategies import models

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "scenes" / "models" / "demo_cheese_small.json"
MATERIALS = {
    "gold": {"type": "conductor", "material": "Au"},
    "red": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.2, 0.1]}},
    "glass": {"type": "dielectric", "int_ior": 1.5},
}


# ---- Helpers ----

def leaf_params(leaf) -> dict:
    """A leaf's parameters read from its slots (not through native.py): everything but derived data."""
    out = {}
    for cls in type(leaf).__mro__:
        for slot in getattr(cls, "__slots__", ()):
            if slot not in ("matrix", "material", "vertices"):
                out[slot] = getattr(leaf, slot)
    return out


def assert_same_leaves(a: Node, b: Node):
    la, lb = a.leaves(), b.leaves()
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        assert type(x) is type(y)
        px, py = leaf_params(x), leaf_params(y)
        assert px.keys() == py.keys()
        for k in px:
            if isinstance(px[k], np.ndarray):
                assert np.array_equal(px[k], py[k]), k
            else:
                assert px[k] == py[k], k
        assert np.array_equal(x.matrix, y.matrix)          # exactly, not approximately
        assert x.material == y.material


def with_random_materials(node: Node, rng: random.Random) -> Node:
    """The same tree with material names on some nodes (operations and leaves)."""
    if isinstance(node, Operation):
        node = Operation(node.kind, [with_random_materials(c, rng) for c in node.children],
                         node.matrix, node.material)
    if rng.random() < 0.3:
        node = node.with_material(rng.choice(sorted(MATERIALS)))
    return node


def doc(root, **extra) -> dict:
    return {"format": "mitsuba-csg", "version": 1, **extra, "root": root}


def sphere(**kw) -> dict:
    return {"type": "sphere", "radius": 1.0, **kw}


def write(tmp_path: Path, content, name="model.json") -> Path:
    path = tmp_path / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif isinstance(content, str):
        path.write_text(content)
    else:
        path.write_text(json.dumps(content))
    return path


def every_primitive_model() -> Node:
    octa = [[sx, sy, sz, 1.0] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    parts = [Sphere(0.5), Box((1, 2, 3)).rotate("z", 30), Cylinder(0.3, 2).rotate((1, 1, 0), 45),
             Cone(0.5, 0.0, 1.0).scale((1, 2, -1)), Torus(1.0, 0.2).translate((0, 0, 1)),
             Prism(6, 0.4, 1.0).with_material("gold"), ConvexPolyhedron(octa).scale(0.7),
             Mesh.from_manifold(manifold3d.Manifold.sphere(0.4, 8)).translate((0.5, 0.0, 0.0))]
    return difference(union(*parts[:4]).with_material("red"), *parts[4:]).translate((0.1, 0.2, 0.3))


def demo_cheese_small() -> Node:
    """The model of scenes/models/demo_cheese_small.json: a box minus 20 spheres, two materials."""
    rng = np.random.default_rng(7)
    centres, radii = rng.uniform(-1, 1, (20, 3)).round(2), rng.uniform(0.15, 0.35, 20).round(2)
    holes = [Sphere(float(r)).translate(c).with_material("cut") for c, r in zip(centres, radii)]
    return difference(Box(2.0), *holes).with_material("cheese")


DEMO_MATERIALS = {
    "cheese": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.95, 0.75, 0.25]}},
    "cut": {"type": "roughplastic", "diffuse_reflectance": {"type": "rgb", "value": [0.9, 0.6, 0.15]},
            "alpha": 0.3},
}


# ---- Round trips ----

@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(model=models(max_leaves=10), seed=st.integers(0, 2**32 - 1))
def test_round_trip_of_random_models_is_exact(model, seed, tmp_path_factory):
    model = with_random_materials(model, random.Random(seed))
    data = to_dict(model, MATERIALS)
    again = from_dict(data)
    assert_same_leaves(model, again)
    assert to_dict(again, MATERIALS) == data                   # same node structure, n-ary kept
    path = tmp_path_factory.mktemp("rt") / "model.json"
    save(model, path, MATERIALS)
    loaded, materials = load_with_materials(path)
    assert_same_leaves(model, loaded)
    assert materials == MATERIALS
    assert json.loads(path.read_text()) == data                # the file is plain JSON


def test_round_trip_keeps_every_primitive_type_and_structure(tmp_path):
    model = every_primitive_model()
    save(model, tmp_path / "m.json", MATERIALS)
    loaded = load(tmp_path / "m.json")
    assert_same_leaves(model, loaded)
    assert isinstance(loaded, Operation) and loaded.kind == "difference" and len(loaded.children) == 5
    assert loaded.children[0].kind == "union" and len(loaded.children[0].children) == 4
    types = [n["type"] for n in to_dict(model)["root"]["children"][0]["children"]]
    assert types == ["sphere", "box", "cylinder", "cone"]


def test_identity_transforms_are_not_written_and_others_are_full_precision():
    data = to_dict(union(Sphere(1), Sphere(1).translate((0, 0, 0)), Sphere(1).translate((0.1, 0, 0))))
    children = data["root"]["children"]
    assert "transform" not in children[0] and "transform" not in children[1]
    assert children[2]["transform"][0] == [1.0, 0.0, 0.0, 0.1]
    assert "transform" not in data["root"] and "materials" not in data


def test_deep_binary_chain_round_trips_without_recursion(tmp_path):
    model = Sphere(1.0)
    for i in range(3000):                        # json's C scanner and encoder stop near 1000
        model = model | Sphere(0.5).translate((i * 0.01, 0, 0))
    save(model, tmp_path / "chain.json")
    loaded = load(tmp_path / "chain.json")
    assert loaded.tree_height() == 3000
    assert_same_leaves(model, loaded)


def test_steps_transform_applies_steps_in_order():
    steps = [{"translate": [1, 0, 0]}, {"rotate": {"axis": "z", "degrees": 90}}, {"scale": [1, 2, 3]},
             {"matrix": [[1, 0, 0, 0], [0, 1, 0, 5], [0, 0, 1, 0], [0, 0, 0, 1]]}, {"scale": 2}]
    node = from_dict(doc(sphere(transform=steps)))
    expected = (Sphere(1.0).translate((1, 0, 0)).rotate("z", 90).scale((1, 2, 3))
                .transform([[1, 0, 0, 0], [0, 1, 0, 5], [0, 0, 1, 0], [0, 0, 0, 1]]).scale(2))
    assert np.array_equal(node.matrix, expected.matrix)
    assert from_dict(doc(sphere(transform=[]))).matrix is not None   # no steps: identity


def test_materials_are_optional_and_inherited(tmp_path):
    node, materials = load_with_materials(write(tmp_path, doc(
        {"type": "union", "material": "a", "children": [sphere(), sphere(material="b")]})))
    assert materials == {} and [leaf.material for leaf in node.leaves()] == ["a", "b"]


def test_demo_file_is_the_documented_model():
    model, materials = load_with_materials(DEMO)
    assert materials == DEMO_MATERIALS
    assert_same_leaves(model, demo_cheese_small())
    assert len(model.leaves()) == 21
    assert DEMO.read_text() == native._document_text(to_dict(demo_cheese_small(), DEMO_MATERIALS))


def test_loads_reads_text():
    text = json.dumps(to_dict(every_primitive_model(), MATERIALS))
    model, materials = native.loads_with_materials(text.encode())
    assert_same_leaves(model, every_primitive_model())
    assert materials == MATERIALS
    with pytest.raises(FormatError, match=r"^<string>: root\.radius: must be > 0, got 0$"):
        native.loads(json.dumps(doc(sphere(radius=0))))
    with pytest.raises(FormatError, match=r"^inline: invalid JSON at line 1, column 1"):
        native.loads("}", source="inline")


def test_documented_example_loads():
    text = (REPO / "docs" / "formats" / "native-json.md").read_text()
    example = re.findall(r"```json\n(.*?)```", text, re.S)[0]
    model, materials = native.from_dict_with_materials(json.loads(example), source="native-json.md")
    assert sorted(materials) == ["cheese", "rind"]
    assert [type(leaf).__name__ for leaf in model.leaves()] == [
        "Box", "Sphere", "Sphere", "Cylinder", "Torus", "Cone", "Prism", "ConvexPolyhedron"]
    assert [leaf.material for leaf in model.leaves()] == ["rind"] + ["cheese"] * 7


# ---- Errors: the message starts with the source and the JSON path ----

def test_message_names_file_and_path_exactly(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    children = [sphere(), sphere(), sphere(), {"type": "sphere", "radius": -1}]
    write(tmp_path, doc({"type": "union", "children": children}))
    with pytest.raises(FormatError) as info:
        load("model.json")
    assert str(info.value) == "model.json: root.children[3].radius: must be > 0, got -1"
    assert isinstance(info.value, ModelError)
    with pytest.raises(FormatError, match=r"^<dict>: root\.children\[3\]\.radius: must be > 0, got -1$"):
        from_dict(doc({"type": "union", "children": children}))
    with pytest.raises(FormatError, match=r"^mine: root\.radius: must be > 0, got 0$"):
        from_dict(doc(sphere(radius=0)), source="mine")


def test_file_errors(tmp_path):
    with pytest.raises(FormatError, match=r"nope\.json: no such file"):
        load(tmp_path / "nope.json")
    with pytest.raises(FormatError, match="is a directory"):
        load(tmp_path)
    with pytest.raises(FormatError, match=r"model\.json: invalid JSON at line 3, column 5: Expecting"):
        load(write(tmp_path, '{\n  "format": "mitsuba-csg",\n    ]'))
    with pytest.raises(FormatError, match=r"invalid JSON at line 1, column 1: Expecting value"):
        load(write(tmp_path, ""))
    with pytest.raises(FormatError, match=r"not UTF-8 text \(invalid byte at offset 2"):
        load(write(tmp_path, b'{"\xff'))
    # beyond Python's int-string limit: named at its path, like NaN or Infinity
    with pytest.raises(FormatError, match=r"root\.radius: must be finite, got a 5000-digit integer"):
        load(write(tmp_path, '{"format": "mitsuba-csg", "version": 1, "root": {"type": "sphere", "radius": '
                   + "9" * 5000 + "}}"))
    bom = "\ufeff" + json.dumps(doc(sphere()))
    assert isinstance(load(write(tmp_path, bom.encode("utf-8"))), Sphere)


@pytest.mark.parametrize("data,pattern", [
    ([1], r"^<dict>: \$: expected a model document"),
    ({"version": 1, "root": sphere()}, r'^<dict>: \$: missing key "format"'),
    ({"format": "csg", "version": 1, "root": sphere()},
     r'^<dict>: format: expected "mitsuba-csg", got the string "csg"'),
    ({"format": "mitsuba-csg", "root": sphere()}, r'^<dict>: \$: missing key "version"'),
    (doc(sphere()) | {"version": 2}, r"^<dict>: version: unsupported version 2; this reader supports version 1$"),
    (doc(sphere()) | {"version": "1"}, r"^<dict>: version: expected an integer version, got the string \"1\"; "
                                       r"this reader supports version 1"),
    (doc(sphere()) | {"version": True}, r"^<dict>: version: expected an integer version, got true"),
    (doc(sphere(), extra=1), r"^<dict>: \$: unknown key\(s\) 'extra'; allowed keys: format, version, materials, root"),
    ({"format": "mitsuba-csg", "version": 1}, r'^<dict>: \$: missing key "root"'),
])
def test_document_errors(data, pattern):
    with pytest.raises(FormatError, match=pattern):
        from_dict(data)


U = "union"


def in_union(node) -> dict:
    return doc({"type": U, "children": [sphere(), node]})


@pytest.mark.parametrize("node,pattern", [
    # node type and keys
    ({"type": "sphre", "radius": 1}, r"root\.children\[1\]\.type: unknown node type 'sphre'; "
                                     r"known node types: box, cone, convex_polyhedron, cylinder, hyperboloid, mesh, "
                                     r"paraboloid, prism, sphere, torus, union, intersection, difference$"),
    ({"radius": 1}, r'root\.children\[1\]: missing key "type"; known node types: box'),
    ([1, 2], r"root\.children\[1\]: expected a node .* got a list of 2 items"),
    ({"type": "sphere"}, r"root\.children\[1\]: a sphere needs 'radius' \(missing\)"),
    ({"type": "cone", "height": 1}, r"root\.children\[1\]: a cone needs 'radius_bottom', 'radius_top'"),
    (sphere(radiu=2, colour=1), r"root\.children\[1\]: unknown key\(s\) 'radiu', 'colour' for a sphere; "
                                r"allowed keys: type, radius, transform, material"),
    ({"type": "union", "children": [], }, r"root\.children\[1\]\.children: a union needs at least one child"),
    ({"type": "union", "children": sphere()}, r"root\.children\[1\]\.children: expected a list of child nodes, "
                                              r"got an object"),
    ({"type": "union", "children": [sphere()], "radius": 1}, r"unknown key\(s\) 'radius' for a union"),
    # value types and ranges
    (sphere(radius="1"), r"root\.children\[1\]\.radius: expected a number, got the string \"1\""),
    (sphere(radius=True), r"root\.children\[1\]\.radius: expected a number, got true"),
    (sphere(radius=None), r"root\.children\[1\]\.radius: expected a number, got null"),
    (sphere(radius=[1]), r"root\.children\[1\]\.radius: expected a number, got a list of 1 item$"),
    (sphere(radius=float("nan")), r"root\.children\[1\]\.radius: must be finite, got NaN"),
    (sphere(radius=float("inf")), r"root\.children\[1\]\.radius: must be finite, got Infinity"),
    (sphere(radius=10**400), r"root\.children\[1\]\.radius: must be finite, got an integer beyond the float range"),
    (sphere(radius=0), r"root\.children\[1\]\.radius: must be > 0, got 0$"),
    ({"type": "box", "size": [1, 2]}, r"root\.children\[1\]\.size: expected 3 numbers, got 2"),
    ({"type": "box", "size": [1, -2, 3]}, r"root\.children\[1\]\.size\[1\]: must be > 0, got -2"),
    ({"type": "box", "size": "big"}, r"root\.children\[1\]\.size: expected a number, got the string"),
    ({"type": "cylinder", "radius": 1, "height": -0.5}, r"root\.children\[1\]\.height: must be > 0, got -0\.5"),
    ({"type": "cone", "radius_bottom": -1, "radius_top": 0, "height": 1},
     r"root\.children\[1\]\.radius_bottom: must be >= 0, got -1"),
    ({"type": "cone", "radius_bottom": 0, "radius_top": 0, "height": 1},
     r"root\.children\[1\]: Cone: radius_bottom and radius_top are both 0"),
    ({"type": "torus", "major_radius": 1, "minor_radius": 2},
     r"root\.children\[1\]: Torus: minor_radius \(2\) must be < major_radius \(1\)"),
    ({"type": "prism", "sides": 6.0, "apothem": 1, "height": 1},
     r"root\.children\[1\]\.sides: expected an integer in 3\.\.1000, got 6\.0"),
    ({"type": "prism", "sides": 2, "apothem": 1, "height": 1}, r"root\.children\[1\]\.sides: expected an integer"),
    ({"type": "prism", "sides": False, "apothem": 1, "height": 1}, r"\.sides: expected an integer .* got false"),
    ({"type": "convex_polyhedron", "planes": [[1, 0, 0, 1]] * 3},
     r"root\.children\[1\]\.planes: a closed convex solid needs 4\.\.16384 planes, got 3"),
    ({"type": "convex_polyhedron", "planes": [[1, 0, 0, 1]] * 3 + [[1, 0, 1]]},
     r"root\.children\[1\]\.planes\[3\]: expected 4 numbers, got 3"),
    ({"type": "convex_polyhedron", "planes": [[1, 0, 0, 1]] * 3 + [[0, 0, 0, 1]]},
     r"root\.children\[1\]\.planes\[3\]: the normal \(nx, ny, nz\) is zero"),
    ({"type": "convex_polyhedron", "planes": [[1, 0, 0, 1], [-1, 0, 0, 1], [0, 1, 0, 1], [0, -1, 0, 1]]},
     r"root\.children\[1\]: ConvexPolyhedron: the planes do not enclose a bounded solid"),
    # transforms
    (sphere(transform="up"), r"root\.children\[1\]\.transform: expected a 4x4 matrix or a list of steps"),
    (sphere(transform=[[1, 0, 0, 0]] * 3), r"\.transform: expected a 4x4 matrix \(4 rows of 4 numbers\), got 3 rows"),
    (sphere(transform=[[1, 0, 0, 0]] * 3 + [[0, 0, 1]]), r"\.transform\[3\]: expected 4 numbers, got 3"),
    (sphere(transform=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]),
     r"root\.children\[1\]\.transform: the last row must be \(0, 0, 0, 1\)"),
    (sphere(transform=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]),
     r"root\.children\[1\]\.transform: singular transform"),
    (sphere(transform=[[1, 0, 0, "x"]] * 4), r"\.transform\[0\]\[3\]: expected a number, got the string"),
    (sphere(transform=[{"translate": [1, 2, 3]}, 5]), r"\.transform\[1\]: expected a step such as"),
    (sphere(transform=[{"move": [1, 2, 3]}]), r"\.transform\[0\]: unknown transform step 'move'; expected one of "
                                              r"translate, rotate, scale, matrix"),
    (sphere(transform=[{"translate": [1, 2, 3], "scale": 2}]), r"\.transform\[0\]: a step has exactly one key"),
    (sphere(transform=[{"translate": [1, 2]}]), r"\.transform\[0\]\.translate: expected 3 numbers, got 2"),
    (sphere(transform=[{"translate": [1, float("nan"), 3]}]), r"\.transform\[0\]\.translate\[1\]: must be finite"),
    (sphere(transform=[{"rotate": {"axis": "z"}}]), r"\.transform\[0\]\.rotate: expected the keys \"axis\" and "
                                                    r"\"degrees\"; missing 'degrees'"),
    (sphere(transform=[{"rotate": {"axis": "w", "degrees": 3}}]), r"\.transform\[0\]\.rotate\.axis: expected \"x\""),
    (sphere(transform=[{"rotate": {"axis": [0, 0, 0], "degrees": 3}}]), r"\.rotate\.axis: the axis must not be"),
    (sphere(transform=[{"rotate": {"axis": "x", "degrees": "90"}}]), r"\.rotate\.degrees: expected a number"),
    (sphere(transform=[{"rotate": 90}]), r"\.transform\[0\]\.rotate: expected a rotation"),
    (sphere(transform=[{"scale": [1, 0, 1]}]), r"\.transform\[0\]\.scale: a zero factor makes the solid flat"),
    (sphere(transform=[{"scale": [1e-200, 1, 1]}]), r"root\.children\[1\]\.transform: singular transform"),
    (sphere(transform=[{"matrix": [[1, 0, 0, 0]]}]), r"\.transform\[0\]\.matrix: expected a 4x4 matrix"),
    # materials on nodes
    (sphere(material=3), r"root\.children\[1\]\.material: expected a material name \(a non-empty string\), got 3"),
    (sphere(material=""), r"root\.children\[1\]\.material: expected a material name"),
])
def test_node_errors_name_the_json_path(node, pattern):
    with pytest.raises(FormatError, match=r"^<dict>: " + (pattern if pattern.startswith("root") else ".*" + pattern)):
        from_dict(in_union(node))


@pytest.mark.parametrize("materials,pattern", [
    ([], r"^<dict>: materials: expected a map from material names"),
    ({"": {"type": "diffuse"}}, r'^<dict>: materials\[""\]: expected a material name'),
    ({"a": "diffuse"}, r"^<dict>: materials\.a: expected a Mitsuba BSDF dict"),
    ({"a": {"reflectance": 0.5}}, r'^<dict>: materials\.a: missing key "type"'),
    ({"a": {"type": 5}}, r"^<dict>: materials\.a\.type: expected a Mitsuba plugin name"),
    ({"a": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, float("nan"), 0.5]}}},
     r"^<dict>: materials\.a\.reflectance\.value\[1\]: must be finite, got NaN"),
    ({"my gold": {"type": "diffuse", "x": object()}}, r'^<dict>: materials\["my gold"\]\.x: expected a JSON value'),
])
def test_material_errors(materials, pattern):
    with pytest.raises(FormatError, match=pattern):
        from_dict(doc(sphere(material="a"), materials=materials))


def test_material_reference_must_be_defined(tmp_path):
    data = doc({"type": "union", "children": [sphere(material="red"), sphere(material="rde")]},
               materials={"red": MATERIALS["red"]})
    with pytest.raises(FormatError, match=r"model\.json: root\.children\[1\]\.material: unknown material 'rde'; "
                                          r'"materials" defines: red$'):
        load(write(tmp_path, data))
    with pytest.raises(FormatError, match=r'root\.material: unknown material \'red\'; "materials" defines: none'):
        from_dict(doc(sphere(material="red"), materials={}))


def test_json_literals_nan_and_infinity_are_refused(tmp_path):
    for literal in ("NaN", "Infinity", "-Infinity", "1e999"):
        text = '{"format": "mitsuba-csg", "version": 1, "root": {"type": "union", "children": [' \
               '{"type": "sphere", "radius": %s}]}}' % literal
        with pytest.raises(FormatError, match=r"model\.json: root\.children\[0\]\.radius: must be finite"):
            load(write(tmp_path, text))
    text = '{"format": "mitsuba-csg", "version": 1, "materials": {"m": {"type": "d", "v": NaN}}, "root": %s}'
    with pytest.raises(FormatError, match=r"model\.json: materials\.m\.v: must be finite, got NaN"):
        load(write(tmp_path, text % json.dumps(sphere())))


def test_duplicate_keys_are_refused(tmp_path):
    text = '{"format": "mitsuba-csg", "version": 1, "root": {"type": "sphere", "radius": 1, "radius": 2}}'
    with pytest.raises(FormatError, match=r"model\.json: root: duplicate key\(s\) 'radius'"):
        load(write(tmp_path, text))


def nested_union_text(depth: int) -> str:
    head = '{"type": "union", "children": ['
    return ('{"format": "mitsuba-csg", "version": 1, "root": ' + head * depth
            + '{"type": "sphere", "radius": 1}' + "]}" * depth + "}")


def test_depth_limit_in_files(tmp_path):
    ok = load(write(tmp_path, nested_union_text(native.MAX_DEPTH)))
    assert ok.tree_height() == native.MAX_DEPTH
    with pytest.raises(FormatError, match=r"model\.json: root(\.children\[0\]){8}<19968 more path segments>"
                                          r"(\.children\[0\]){8}\.children: the tree is nested deeper than "
                                          r"10000 operation levels"):
        load(write(tmp_path, nested_union_text(native.MAX_DEPTH + 1)))
    # Far deeper than the limit: refused by the parser, fast, without RecursionError.
    with pytest.raises(FormatError, match=r"model\.json: invalid JSON at line 1, column \d+: nested deeper than"):
        load(write(tmp_path, "[" * 1_000_000 + "]" * 1_000_000))


def test_depth_limit_in_dicts():
    root = sphere()
    for _ in range(native.MAX_DEPTH + 1):
        root = {"type": "union", "children": [root]}
    with pytest.raises(FormatError, match=r"^<dict>: root.*: the tree is nested deeper than 10000"):
        from_dict(doc(root))
    cyclic = {"type": "union", "children": []}
    cyclic["children"].append(cyclic)
    with pytest.raises(FormatError, match="nested deeper than"):
        from_dict(doc(cyclic))


def test_node_count_limit(monkeypatch, tmp_path):
    monkeypatch.setattr(native, "MAX_NODES", 50)
    assert len(from_dict(doc({"type": "union", "children": [sphere()] * 49})).leaves()) == 49
    with pytest.raises(FormatError, match=r"^<dict>: root\.children: the document has more than 50 nodes"):
        from_dict(doc({"type": "union", "children": [sphere()] * 50}))
    with pytest.raises(ModelError, match="more than 50 nodes"):
        save(union(*[Sphere(1)] * 60), tmp_path / "big.json")


def test_save_errors(tmp_path, monkeypatch):
    with pytest.raises(ModelError, match=r"uses material\(s\) blue that `materials` does not define"):
        save(Sphere(1).with_material("blue"), tmp_path / "m.json", MATERIALS)
    with pytest.raises(ModelError, match=r"to_dict: expected a CSG node, got dict"):
        to_dict({"type": "sphere"})
    with pytest.raises(FormatError, match=r"to_dict: materials\.red\.value: must be finite, got NaN"):
        to_dict(Sphere(1), {"red": {"type": "diffuse", "value": float("nan")}})
    for degenerate in (Sphere(1).scale((1e-7, 1, 1)).scale((1e-7, 1, 1)), Sphere(1).scale(1e200).scale(1e200)):
        with pytest.raises(ModelError, match=r"to_dict: node 2 \(depth-first order, a sphere\) has a local matrix"):
            to_dict(union(Sphere(1), degenerate))
    monkeypatch.setattr(native, "MAX_DEPTH", 3)
    with pytest.raises(ModelError, match="nested deeper than 3 operation levels"):
        to_dict(Sphere(1) | Sphere(1) | Sphere(1) | Sphere(1) | Sphere(1))
    assert not (tmp_path / "m.json").exists()


# ---- The iterative JSON parser (used for files too deep for json.loads) ----

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**20, 10**20) | st.text(max_size=5)
    | st.floats(allow_nan=False, allow_infinity=False),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner, max_size=4),
    max_leaves=20)


def reference_parse(text):
    return json.loads(text, parse_constant=native._NonFinite, object_pairs_hook=native._object_pairs)


@given(value=json_values, indent=st.sampled_from([None, 0, 2]), cut=st.integers(0, 400))
def test_iterative_parser_equals_json_loads(value, indent, cut):
    text = json.dumps(value, indent=indent, ensure_ascii=indent is None)
    assert native._parse_iteratively(text, 1000) == reference_parse(text)
    broken = text[:cut] + text[cut + 1:] if cut < len(text) else text + ","
    try:
        expected = reference_parse(broken)
    except json.JSONDecodeError as e:
        with pytest.raises(json.JSONDecodeError) as info:
            native._parse_iteratively(broken, 1000)
        assert (info.value.msg, info.value.pos) == (e.msg, e.pos)
    else:
        assert native._parse_iteratively(broken, 1000) == expected


def test_iterative_parser_details():
    text = '{"a": [NaN, -Infinity, 1e400, -0.0, 12, "x\\u00e9"], "a": {}, "b": [[], {}]}'
    got = native._parse_iteratively(text, 10)
    assert isinstance(got, native._DuplicateKeys) and got.duplicates == ["a"]
    value = reference_parse(text)["b"]
    assert got["b"] == value
    nan, minf, big, zero, twelve, s = native._parse_iteratively(text.replace('"a": {}, ', ""), 10)["a"]
    assert (nan.literal, minf.literal, big, math.copysign(1, zero), twelve, s) == ("NaN", "-Infinity", math.inf,
                                                                                  -1.0, 12, "x\u00e9")
    for bad in ("[1,]", '{"a" 1}', "[1 2]", "01", "[", "", "tru", '{"a":1,}', "[1]x"):
        with pytest.raises(json.JSONDecodeError) as info:
            native._parse_iteratively(bad, 10)
        with pytest.raises(json.JSONDecodeError) as expected:
            reference_parse(bad)
        assert (info.value.msg, info.value.pos) == (expected.value.msg, expected.value.pos), bad


# ---- Fuzz: mutated files raise FormatError/ModelError and nothing else ----

def _slots(data):
    """Every (container, key) position in a JSON value, found iteratively."""
    out, stack = [], [data]
    while stack:
        v = stack.pop()
        items = v.items() if isinstance(v, dict) else enumerate(v) if isinstance(v, list) else ()
        for k, item in items:
            out.append((v, k))
            stack.append(item)
    return out


def _mutate_data(data, rng: random.Random):
    data = copy.deepcopy(data)
    for _ in range(rng.randint(1, 3)):
        slots = _slots(data)
        container, key = rng.choice(slots)
        what = rng.random()
        if what < 0.25 and isinstance(container, dict):
            del container[key]
        elif what < 0.5:
            container[key] = rng.choice([None, True, False, "x", "", [], {}, [1, 2, 3], {"type": "sphere"},
                                         0, 1, -1, 2.5, [[1, 0, 0, 0]] * 4, "union", "sphere"])
        elif what < 0.8:
            old = container[key]
            numeric = isinstance(old, (int, float)) and not isinstance(old, bool) and abs(old) < 1e15
            scale = old if numeric else 1
            container[key] = rng.choice([-scale, 0, float("nan"), float("inf"), -float("inf"), 1e308, -1e308,
                                         10**400, 1e-308, scale * 1e6, int(abs(scale) * 7) + 2])
        elif isinstance(container, list) and container:
            container.append(copy.deepcopy(container[0]))
        elif isinstance(container, dict):
            container[rng.choice(["extra", "type", "children", "transform", "material"])] = \
                copy.deepcopy(rng.choice([v for _, v in slots[:8]] or [1]))
    return data


def _mutate_text(text: bytes, rng: random.Random) -> bytes:
    what = rng.random()
    if what < 0.3:
        return text[:rng.randrange(len(text))]
    if what < 0.6:
        b = bytearray(text)
        for _ in range(rng.randint(1, 4)):
            b[rng.randrange(len(b))] = rng.randrange(256)
        return bytes(b)
    if what < 0.8:
        i = rng.randrange(len(text))
        return text[:i] + bytes(rng.randrange(256) for _ in range(rng.randint(1, 6))) + text[i:]
    i, j = sorted(rng.randrange(len(text)) for _ in range(2))
    return text[:i] + text[j:]


def test_fuzz_mutated_documents_raise_only_model_errors(tmp_path):
    seeds = [to_dict(every_primitive_model(), MATERIALS),
             to_dict(demo_cheese_small(), DEMO_MATERIALS),
             doc({"type": "intersection", "material": "m", "transform": [
                 {"translate": [1, 2, 3]}, {"rotate": {"axis": [1, 1, 0], "degrees": 30}}, {"scale": [1, 2, 3]},
                 {"matrix": np.eye(4).tolist()}], "children": [sphere(), {"type": "box", "size": 1}]},
                 materials={"m": {"type": "diffuse"}})]
    rng = random.Random(1234)
    path = tmp_path / "fuzz.json"
    outcomes = {"ok": 0, "error": 0}
    for i in range(1500):
        base = seeds[i % len(seeds)]
        if rng.random() < 0.5:
            text = json.dumps(_mutate_data(base, rng)).encode()        # NaN/Infinity literals included
        else:
            text = _mutate_text(json.dumps(base, indent=rng.choice([None, 1])).encode(), rng)
        path.write_bytes(text)
        try:
            load_with_materials(path)
            outcomes["ok"] += 1
        except ModelError as e:                      # FormatError is a ModelError
            assert str(e).startswith(str(path) + ": "), str(e)
            outcomes["error"] += 1
        # anything else (TypeError, KeyError, RecursionError, OverflowError, ...) fails the test
    assert outcomes["error"] > 1000 and outcomes["ok"] > 20, outcomes


def test_fuzz_dicts_from_python_raise_only_model_errors():
    rng = random.Random(99)
    base = to_dict(every_primitive_model(), MATERIALS)
    for _ in range(500):
        data = _mutate_data(base, rng)
        if rng.random() < 0.2:         # Python-only values json never produces
            container, key = rng.choice(_slots(data))
            container[key] = rng.choice([object(), (1, 2, 3), {1: 2}, np.float64(np.nan), np.int64(3), b"x"])
        try:
            from_dict(data)
        except ModelError as e:
            assert str(e).startswith("<dict>: ")


def test_load_refuses_options_the_format_does_not_take(tmp_path):
    import mitsuba_csg as csg
    path = tmp_path / "m.json"
    save(Sphere(1.0), path)
    with pytest.raises(csg.CSGError, match="on_unsupported.*|takes no options"):
        csg.load(path, on_unsupported="skip")
    with pytest.raises(csg.CSGError, match="solid, depth, show_world, on_unsupported"):
        csg.load(tmp_path / "m.gdml", solids="x")
