"""Kernel accuracy against the float64 interval reference on random trees (issue 2's figures).

    ./run.sh bench accuracy.py [--models 200] [--rays 256]

Random models from the test strategies (every primitive, operation and transform kind),
rays aimed at their primitives; traced as lowered (general form), positive form and
optimized. Reports, per form: rays, the share the reference calls well-conditioned
("stable"), and on those: hit/miss, primitive, entering agreement, the worst relative t
error and the worst normal angle.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

import common

sys.path.insert(0, str(common.ROOT / "tests"))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", type=int, default=200)
    parser.add_argument("--rays", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    from hypothesis import strategies as st  # noqa: F401  (the strategies need hypothesis)

    import mitsuba_csg as csg
    import reference as ref
    from strategies import make_rays, models
    forms = {"general": dict(optimize=False), "positive": dict(optimize=False, positive=True),
             "optimized": dict(optimize=True)}
    totals = {f: dict(form=f, models=0, rays=0, stable=0, hit_agree=0, prim_agree=0, enter_agree=0,
                      hits=0, max_t_rel=0.0, max_normal_deg=0.0, unfinished=0) for f in forms}
    strategy = models(max_leaves=10)
    rng = np.random.default_rng(args.seed)
    for k in range(args.models):
        model = strategy.example()
        o, d = make_rays(int(rng.integers(2**31)), args.rays, targets=[leaf.matrix[:3, 3] for leaf in model.leaves()])
        t_ref, prim_ref, n_ref, enter_ref = ref.first_hit(model, o, d)
        stable = ref.stable_mask(model, o, d)
        for form, kw in forms.items():
            h = csg.trace(csg.prepare(model, **kw), o, d)
            row = totals[form]
            row["models"] += 1
            row["rays"] += len(o)
            row["unfinished"] += h.unfinished
            s = stable
            row["stable"] += int(s.sum())
            hit_ref, hit_k = np.isfinite(t_ref[s]), np.isfinite(h.t[s])
            row["hit_agree"] += int((hit_ref == hit_k).sum())
            both = hit_ref & hit_k
            row["hits"] += int(both.sum())
            row["prim_agree"] += int((h.prim[s][both] == prim_ref[s][both]).sum())
            row["enter_agree"] += int((h.entering[s][both] == enter_ref[s][both]).sum())
            if both.any():
                rel = np.abs(h.t[s][both] - t_ref[s][both]) / np.maximum(1.0, np.abs(t_ref[s][both]))
                cosang = np.clip(np.einsum("ij,ij->i", h.normal[s][both], n_ref[s][both]), -1, 1)
                row["max_t_rel"] = max(row["max_t_rel"], float(rel.max()))
                row["max_normal_deg"] = max(row["max_normal_deg"], float(np.degrees(np.arccos(cosang)).max()))
    rows = []
    for row in totals.values():
        row["stable_pct"] = 100.0 * row["stable"] / row["rays"]
        row["hit_agree_pct"] = 100.0 * row["hit_agree"] / max(1, row["stable"])
        row["prim_agree_pct"] = 100.0 * row["prim_agree"] / max(1, row["hits"])
        row["enter_agree_pct"] = 100.0 * row["enter_agree"] / max(1, row["hits"])
        rows.append(row)
    columns = [("form", "form", "s"), ("models", "models", "d"), ("rays", "rays", "d"), ("stable_pct", "stable %", ".2f"),
               ("hits", "hits", "d"), ("hit_agree_pct", "hit/miss %", ".4f"), ("prim_agree_pct", "prim %", ".4f"),
               ("enter_agree_pct", "enter %", ".4f"), ("max_t_rel", "max t rel err", ".2e"),
               ("max_normal_deg", "max normal deg", ".3f"), ("unfinished", "unfinished", "d")]
    print(common.table(rows, columns))
    print(f"wrote {common.write('accuracy', {'machine': common.machine(), 'args': vars(args), 'rows': rows})}")


if __name__ == "__main__":
    main()
