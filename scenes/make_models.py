"""Write the model files the example scenes use (seeded, so the files are reproducible).

    ./run.sh -- python scenes/make_models.py
"""
from pathlib import Path

import mitsuba_csg as csg
from mitsuba_csg.scenes import cheese

HERE = Path(__file__).resolve().parent


def main():
    (HERE / "models").mkdir(exist_ok=True)
    # The demo Cheese with a golden rind: the cube is 'cheese', the holes 'hole'.
    holes = cheese(500, seed=0)
    box, *spheres = holes.children
    model = csg.difference(box.with_material("cheese"), *(s.with_material("hole") for s in spheres))
    materials = {
        "cheese": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.85, 0.65, 0.25]}},
        "hole": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.75, 0.5, 0.15]}},
    }
    csg.save(model, HERE / "models" / "cheese_500.json", materials=materials)


if __name__ == "__main__":
    main()
