"""Comparison of kernel hits with the float64 reference, with the tolerances the suite states."""
from __future__ import annotations

import numpy as np

import reference as ref

T_REL = 1e-4        # t agrees to 1e-4 relative (to max(1, |t|) in units of |d|)
NORMAL_DOT = 0.999  # normals agree to ~2.5 degrees


def compare(model, hits, o, d, tmin=0.0, tmax=np.inf, *, check_prim=True, coincident=False):
    """Assert agreement on the rays the reference calls stable; returns (stable count, total).

    With `coincident`, faces that coincide (in exact arithmetic: within 1e-9 relative) are
    one surface, so rays meeting them still count; either primitive may be the one reported.
    """
    t_ref, prim_ref, n_ref, enter_ref = ref.first_hit(model, o, d, tmin, tmax)
    stable = ref.stable_mask(model, o, d, tmin, tmax, same=1e-9 if coincident else 0.0)
    check_prim = check_prim and not coincident
    assert hits.unfinished == 0
    s = stable
    hit_ref = np.isfinite(t_ref[s])
    hit_k = np.isfinite(hits.t[s])
    bad = np.flatnonzero(hit_ref != hit_k)
    assert not len(bad), _report("hit/miss", model, o[s], d[s], t_ref[s], hits.t[s], bad)
    both = hit_ref
    scale = np.maximum(1.0, np.abs(t_ref[s][both])) * 1.0
    err = np.abs(hits.t[s][both] - t_ref[s][both]) / scale
    bad = np.flatnonzero(err > T_REL)
    assert not len(bad), _report("t", model, o[s][both], d[s][both], t_ref[s][both], hits.t[s][both], bad)
    if check_prim:
        bad = np.flatnonzero(hits.prim[s][both] != prim_ref[s][both])
        assert not len(bad), _report("prim", model, o[s][both], d[s][both], prim_ref[s][both],
                                     hits.prim[s][both], bad)
    dots = np.einsum("ij,ij->i", hits.normal[s][both], n_ref[s][both])
    bad = np.flatnonzero(dots < NORMAL_DOT)
    assert not len(bad), _report("normal", model, o[s][both], d[s][both], n_ref[s][both], hits.normal[s][both], bad)
    bad = np.flatnonzero(hits.entering[s][both] != enter_ref[s][both])
    assert not len(bad), _report("entering", model, o[s][both], d[s][both], enter_ref[s][both],
                                 hits.entering[s][both], bad)
    return int(s.sum()), len(o)


def _report(what, model, o, d, expected, got, bad):
    i = bad[0]
    return (f"{what} disagrees on {len(bad)} stable rays; first: o={o[i].tolist()} d={d[i].tolist()} "
            f"expected {expected[i]!r} got {got[i]!r}\nmodel: {model!r}")
