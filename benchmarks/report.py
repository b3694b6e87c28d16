"""Write docs/benchmarks.md from the JSON files in benchmarks/results/.

    ./run.sh bench report.py
"""
from __future__ import annotations

import json

import common

PAPER_GTX680 = {  # Table 2 of Bogolepov et al. 2013: GTX 680 frames/s, '-' and '+'
    "city-3385": (51, 57), "city-343k": (8, 22), "city-987k": (8.3, 21), "cheese-500": (11.2, 211),
    "cheese-1000": (5.8, 128), "cheese-8000": (0.5, 32), "cheese-32000": (None, 4),
    "satellites-87.5k": (29, 65), "satellites-1.12M": (7, 15),
}


def load(name):
    path = common.RESULTS / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def fmt(v, spec):
    return "-" if v is None or v != v else format(v, spec)


def by_scene(rows):
    """(scene, input-tree row, optimized row) of trace_throughput.py's rows, in their order."""
    for scene in dict.fromkeys(r["scene"] for r in rows):
        yield (scene, next(r for r in rows if r["scene"] == scene and r["tree"] == "-"),
               next(r for r in rows if r["scene"] == scene and r["tree"] == "+"))


def main():
    out = ["# Benchmarks", "",
           "Numbers from the scripts in `benchmarks/` (each prints a table and writes JSON to "
           "`benchmarks/results/`); this page is written by `./run.sh bench report.py`. "
           "Ratios compare variants measured in the same run. Timings on this shared 2-core machine vary "
           "by up to 2x between runs; the minimum of several runs is reported.", ""]
    t2 = load("table2")
    large = load("table2_large")          # the 1M-primitive rows, run separately (they take minutes)
    if t2 and large:
        t2 = dict(t2, rows=t2["rows"] + large["rows"])
    if t2:
        m = t2["machine"]
        out += ["## Table 2 of the paper, reproduced", "",
                f"Machine: {m['cpu']}, {m['cores']} cores, Mitsuba {m['mitsuba']}, Dr.Jit {m['drjit']}, "
                f"variant `{m['variant']}`, {m['date']}. Command: "
                "`./run.sh bench trace_throughput.py --scenes <scenes> --no-compile --repeats 2 --name table2` "
                "(and `--name table2_large --no-path` for the two largest scenes"
                + (f", run {large['machine']['date']}" if large else "") + "); `--scenes paper` runs all "
                "nine in one go (about a quarter of an hour here).", "",
                f"1280x720 primary rays (one per pixel, no shading; traced in "
                f"{'4x4 pixel tiles' if m.get('ray_order') == 'tiles' else 'image rows'}). "
                "'-': the input tree with chains of one "
                "operation balanced in input order; '+': optimized (paper §4). 'path' is a full `csg_path` "
                "frame at 1 spp (camera, sun shadow ray, one bounce) on the optimized tree.", "",
                "| scene | prims | depth - / + | fps - | fps + | Mrays/s + | steps/ray + | +/- | path 1spp s | "
                "GTX 680 fps - / + (paper) |",
                "|---|---|---|---|---|---|---|---|---|---|"]
        for scene, minus, plus in by_scene(t2["rows"]):
            paper = PAPER_GTX680.get(scene, (None, None))
            out.append(f"| {scene} | {plus['primitives']} | {minus['depth']} / {plus['depth']} | "
                       f"{fmt(minus.get('fps'), '.2f') if 'fps' in minus else minus.get('note', '-')} | "
                       f"{fmt(plus.get('fps'), '.2f')} | {fmt(plus.get('mrays_s'), '.2f')} | "
                       f"{fmt(plus.get('mean_steps'), '.0f')} | {fmt(plus.get('speedup'), '.1f')} | "
                       f"{fmt(plus.get('path_1spp_s'), '.2f')} | {fmt(paper[0], 'g')} / {fmt(paper[1], 'g')} |")
        out.append("")
    cheese = load("table2_cheese")
    if cheese:
        m = cheese["machine"]
        out += ["## The Cheese families, with the traversal mechanisms", "",
                f"`./run.sh bench trace_throughput.py --scenes cheese-500,cheese-1000,cheese-8000,cheese-cp-1000,"
                f"cheese-cp-8000 --no-compile --no-path --repeats 2 --name table2_cheese` ({m['date']}, "
                f"`{m['variant']}`). The paper's generator keeps the hole radii as the count grows, so Cheese-8000 "
                "is almost all holes; `cheese-cp-N` scales the radii so that Cheese-500's solid fraction holds "
                "(`scenes.constant_porosity_cheese`). 'solid' is the solid fraction of the cube, 'holes/ray' the "
                "mean number of holes a camera ray that enters the cube crosses before its visible hit "
                "(`benchmarks/cheese_statistics.py`, float64, from the generator's holes).", "",
                "| scene | prims | solid | holes/ray | steps/ray + | Mrays/s + | steps/ray - | Mrays/s - |",
                "|---|---|---|---|---|---|---|---|"]
        for scene, minus, plus in by_scene(cheese["rows"]):
            out.append(f"| {scene} | {plus['primitives']} | {fmt(plus.get('solid_fraction'), '.3f')} | "
                       f"{fmt(plus.get('holes_crossed'), '.1f')} | {fmt(plus.get('mean_steps'), '.1f')} | "
                       f"{fmt(plus.get('mrays_s'), '.2f')} | {fmt(minus.get('mean_steps'), '.1f')} | "
                       f"{fmt(minus.get('mrays_s'), '.2f') if 'mrays_s' in minus else minus.get('note', '-')} |")
        out.append("")
    tt = load("trace_throughput")
    if tt:
        out += ["## Kernel compile time", "",
                "`./run.sh bench trace_throughput.py` (cold: a fresh process with an empty Dr.Jit kernel cache; "
                "LLVM compile time from Dr.Jit's kernel history).", "",
                "| scene | kernel ops | LLVM compile s (cold) | first trace s (cold) | first trace s (warm cache) |",
                "|---|---|---|---|---|"]
        for r in tt["rows"]:
            if "compile_s" in r:
                out.append(f"| {r['scene']} | {r['kernel_ops']} | {r['compile_s']:.2f} | {r['first_trace_cold_s']:.2f} | "
                           f"{r['first_trace_warm_cache_s']:.2f} |")
        out.append("")
    opt = load("optimizer_scaling")
    if opt:
        out += ["## Optimizer scaling (City)", "", "`./run.sh bench optimizer_scaling.py`", "",
                "| prims | build model s | optimize s | height input / lowered / optimized | nodes before / after | "
                "trace Mrays/s (1280x720, optimized) | peak RSS GB |", "|---|---|---|---|---|---|---|"]
        for r in opt["rows"]:
            out.append(f"| {r['primitives']} | {r['build_model_s']:.1f} | {r['optimize_s']:.1f} | "
                       f"{r['height_input']} / {r['height_before']} / {r['height_after']} | "
                       f"{r['nodes_before']} / {r['nodes_after']} | {fmt(r.get('mrays_s'), '.2f')} | "
                       f"{r['peak_rss_gb']:.1f} |")
        out.append("")
    mech = load("traversal_mechanisms")
    if mech:
        m = mech["machine"]
        w, h = mech["size"]
        out += ["## Traversal mechanisms", "",
                f"`./run.sh bench traversal_mechanisms.py` ({m['date']}, `{m['variant']}`): the optimized tree of "
                f"each scene traced at {w}x{h} with no mechanism (Kensler's automaton as in the paper), each "
                "mechanism alone, all but one, and all (the default); `docs/algorithm.md` describes them. "
                "Steps are automaton iterations plus set-walk iterations (each one node of a set visited) per "
                "primary ray; ratios are against the first row of the scene, "
                "measured in the same run. Table 2 above predates the mechanisms where its date is earlier.", "",
                "| scene | mechanisms | steps/ray | max steps | steps ratio | Mrays/s | speed-up |",
                "|---|---|---|---|---|---|---|"]
        for r in mech["rows"]:
            out.append(f"| {r['scene']} | {r['mechanisms']} | {r['mean_steps']:.1f} | {r['max_steps']} | "
                       f"{r['steps_ratio']:.2f} | {r['mrays_s']:.2f} | {r['speedup']:.2f} |")
        out.append("")
    mesh = load("mesh_route")
    if mesh:
        # A separate run's rows (a scene whose union Boolean needs --compose, or other segments).
        extra = load("mesh_route_satellites")
        for r in (extra or {}).get("rows", []):
            mesh["rows"].append(dict(r, scene=f"{r['scene']} ({extra['args']['segments']} segments"
                                     f"{', composed' if extra['args'].get('compose') else ''}, "
                                     f"{extra['machine']['date']})"))
        order = mesh["machine"].get("ray_order", "rows")
        out += ["## Versus the mesh route", "",
                f"`./run.sh bench mesh_route.py` ({mesh['machine']['date']}, {mesh['machine']['cpu']}, "
                f"{mesh['machine']['cores']} cores, `{mesh['machine']['variant']}`, "
                f"segments={mesh['args']['segments']}, camera rays in "
                f"{'4x4 pixel tiles' if order == 'tiles' else 'image rows'}): manifold3d booleans, "
                "Mitsuba scene build (Embree BVH), Embree primary rays at 1280x720, against optimize + CSG primary rays. "
                "A row with its own segments comes from a separate run (`--compose`: a top-level union's children "
                "meshed one by one and composed, where the union Boolean ran out of memory).",
                "The last columns render one 1-spp frame of the command line's model scene (floor, sky, sun, "
                "max_depth 6) both ways: `csg_path` on the CSG shape, Mitsuba's `path` with the mesh in its place.",
                "'frozen' replays the recorded kernels (`trace_rays(frozen=True)`, as a render loop of fixed "
                "size can) instead of tracing them in Python per frame. The traced, frozen and Embree frames (and "
                "the csg_path and path frames) run in turn, round after round, each reported as its best round: "
                "the ratios do not drift with the speed of a shared machine.",
                "", "| scene | prims | mesh triangles | booleans s | scene build s | Embree s/frame | optimize s | "
                "CSG s/frame | CSG / Embree per frame | frozen CSG s / Embree | first frame: mesh s / CSG s | path s | "
                "csg_path s | csg_path / path |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in mesh["rows"]:
            out.append(f"| {r['scene']} | {r['primitives']} | {r['triangles']} | {r['boolean_s']:.2f} | "
                       f"{r['scene_build_s']:.2f} | {r['embree_s']:.3f} | {r['csg_prepare_s']:.2f} | "
                       f"{r['csg_trace_s']:.3f} | {r['trace_ratio']:.1f} | "
                       f"{fmt(r.get('csg_frozen_s'), '.3f')} / {fmt(r.get('frozen_ratio'), '.1f')} | "
                       f"{r['mesh_first_frame_s']:.2f} / "
                       f"{r['csg_first_frame_s']:.2f} | {fmt(r.get('mesh_path_s'), '.2f')} | "
                       f"{fmt(r.get('csg_path_s'), '.2f')} | {fmt(r.get('path_ratio'), '.1f')} |")
        out.append("")
    if mesh:
        worst = max(mesh["rows"], key=lambda r: r["trace_ratio"])
        steps = next((r["mean_steps"] for r in (t2 or {}).get("rows", [])
                      if r["scene"] == worst["scene"] and r["tree"] == "+" and "mean_steps" in r), None)
        steps = steps or next((r["mean_steps"] for r in (mech or {}).get("rows", [])
                               if r["scene"] == worst["scene"] and r["mechanisms"].startswith("all (")), None)
        steps_text = f"{steps:.0f} steps per ray in {worst['scene']}" if steps else "many steps"
        best = min(mesh["rows"], key=lambda r: r["trace_ratio"])
        out += ["### Where the mesh route is faster, and why", "",
                f"Per frame, the CSG kernel takes {best['trace_ratio']:.1f}x ({best['scene']}) to "
                f"{worst['trace_ratio']:.0f}x ({worst['scene']}) the time of Embree on the tessellated mesh on this CPU"
                + (f" (below 1 on {', '.join(r['scene'] for r in mesh['rows'] if r['trace_ratio'] < 1)}: "
                   "faster than Embree on its mesh). " if best["trace_ratio"] < 1 else ". ") +
                "Embree traverses one hand-tuned BVH over triangles, one ray at a time; our kernel runs "
                "Kensler's automaton, with unions of leaves searched as sets (n-ary nodes walked as a BVH, "
                f"`docs/algorithm.md`), in vectorized steps (the steps/ray column: {steps_text}), each a step of "
                "all 16 lanes of an AVX-512 packet that waits for its slowest lane, with gathers from per-lane "
                "stacks. Overlapping holes make the walks long: a ray crosses every hole on its way to the "
                "solid, which is why the Cheese scales worst, as in the paper; where the holes leave almost no "
                "solid (a Cheese-8000 mesh has a few hundred triangles) Embree has almost nothing to trace "
                "while the kernel still crosses the holes. What the mesh route pays instead is the boolean "
                "evaluation: the first frame costs "
                f"{worst['mesh_first_frame_s']:.1f} s against {worst['csg_first_frame_s']:.1f} s for {worst['scene']}, "
                "every edit of the model pays it again, and the mesh is only as exact as its tessellation.", ""]
    leaves = load("mesh_leaves")
    if leaves:
        m = leaves["machine"]
        out += ["## Mesh leaves", "",
                f"`./run.sh bench mesh_leaves.py` ({m['date']}, `{m['variant']}`, 1280x720 primary rays): a lone "
                "mesh leaf (a warped sphere, non-convex) against Embree on the same triangles, and the Cheese with "
                "its spheres replaced by sphere meshes against the analytic Cheese, in one run; 'frozen' as above.",
                "", "| scene | CSG s/frame | Embree s/frame | CSG / Embree | frozen s/frame | frozen / Embree | "
                "vs sphere holes | steps/ray |", "|---|---|---|---|---|---|---|---|"]
        for r in leaves["rows"]:
            out.append(f"| {r['scene']} | {r['csg_s']:.3f} | {fmt(r.get('embree_s'), '.3f')} | "
                       f"{fmt(r.get('ratio'), '.1f')} | {fmt(r.get('csg_frozen_s'), '.3f')} | "
                       f"{fmt(r.get('frozen_ratio'), '.1f')} | {fmt(r.get('vs_analytic'), '.2f')} | "
                       f"{r['mean_steps']:.1f} |")
        out.append("")
    incoherent = load("incoherent_rays")
    if incoherent:
        m = incoherent["machine"]
        out += ["## Incoherent ray batches", "",
                f"`./run.sh bench incoherent_rays.py` ({m['date']}, `{m['variant']}`): "
                "batches traced as given and with "
                "`trace_rays(reorder=True)` (only the rays that meet the model's box, sorted by origin and "
                "direction cell; the sort included), and by Embree on the manifold3d mesh. `bounce`: points "
                "on the ground under the model with cosine-distributed upward directions; `points`: points "
                "uniform in the model's box, each with the fixed direction of `csg.contains`; `surface`: the "
                "benchmark camera's hits on the model, each continued in a cosine-distributed direction about "
                "its normal (a path tracer's first bounce off the model), also traced with each ray's start "
                "primitive (`trace_rays(start_prim=...)`, as csg_path passes it: 'hinted'). Steps per ray of "
                "the rays in the box that hit the model and that leave it are given apart. SIMD use is the "
                "mean steps over the mean of each 16-lane packet's largest, for the batch as given.", "",
                "| scene | batch | rays | rays in box | steps/ray | steps/ray hit / leave | SIMD use | as given s | "
                "reordered s | speed-up | hinted steps/ray | hinted s | Embree s | as given / Embree | "
                "reordered / Embree | hinted / Embree |",
                "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in incoherent["rows"]:
            given = r["plain_s"] / r["embree_s"] if r.get("embree_s") else None
            hinted = r["hinted_s"] / r["embree_s"] if r.get("embree_s") and r.get("hinted_s") else None
            out.append(f"| {r['scene']} | {r['batch']} | {r['rays']} | {r['box_fraction']:.2f} | "
                       f"{r['mean_steps']:.1f} | {fmt(r.get('steps_hit'), '.1f')} / {fmt(r.get('steps_leave'), '.1f')} | "
                       f"{r['utilization']:.2f} | {r['plain_s']:.3f} | {r['reorder_s']:.3f} | {r['speedup']:.2f} | "
                       f"{fmt(r.get('steps_hinted'), '.1f')} | {fmt(r.get('hinted_s'), '.3f')} | "
                       f"{fmt(r.get('embree_s'), '.3f')} | {fmt(given, '.1f')} | "
                       f"{fmt(r.get('reorder_over_embree'), '.1f')} | {fmt(hinted, '.1f')} |")
        out.append("")
    depths = load("path_depths")
    if depths:
        m = depths["machine"]
        out += ["## csg_path frames by path depth", "",
                f"`./run.sh bench path_depths.py` ({m['date']}, `{m['variant']}`): 1-spp {depths['args']['size']} "
                "frames of mesh_route.py's scene (floor, sky, sun, one diffuse BSDF) with `max_depth` set per "
                "row: `csg_path` on the CSG shape and Mitsuba's `path` on its manifold3d mesh, and both on a "
                "box of the model's bounds, which costs each integrator what it spends besides tracing the "
                "model. 'CSG traversal' is csg_path's frame less its box frame, 'Embree traversal' path's less "
                "its box frame: what tracing the model adds to each on the camera, shadow and bounce rays of "
                "a path tracer (many of which start on the model, inside the Cheese's holes).", "",
                "| scene | max_depth | csg_path s | path s | csg_path / path | csg_path box s | path box s | "
                "CSG traversal s | Embree traversal s | traversal ratio |",
                "|---|---|---|---|---|---|---|---|---|---|"]
        for r in depths["rows"]:
            out.append(f"| {r['scene']} | {r['max_depth']} | {r['csg_path_s']:.3f} | {r['path_s']:.3f} | "
                       f"{r['ratio']:.2f} | {r['csg_path_s_bare']:.3f} | {r['path_s_bare']:.3f} | "
                       f"{r['csg_traversal_s']:.3f} | {r['embree_traversal_s']:.3f} | "
                       f"{fmt(r['traversal_ratio'], '.1f')} |")
        out.append("")
    several = load("several_shapes")
    if several:
        m = several["machine"]
        out += ["## Several csg shapes in one scene", "",
                f"`./run.sh bench several_shapes.py` ({m['date']}, `{m['variant']}`): a grid of small Cheeses "
                f"({several['rows'][0]['holes']} holes each) as separate csg shapes. Primary rays at "
                f"{several['size']}: one traversal per shape, each up to the nearest hit so far (the integrators "
                "before shapes were grouped), one traversal of the shapes' group (GROUP nodes over the shapes' "
                "roots, `engine.grouping`; the integrators now), and the same geometry as one optimized union "
                "(one shape). Then 1-spp frames (floor, sky, sun, max_depth 6): `csg_path` with the Cheeses as "
                "separate shapes and as one, and Mitsuba's `path` on the manifold3d mesh of the union.",
                "", "| shapes | per shape ms | grouped ms | one union ms | per shape / grouped | steps/ray per "
                "shape (sum) | grouped | union | csg_path shapes s | csg_path one shape s | path on mesh s |",
                "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in several["rows"]:
            out.append(f"| {r['shapes']} | {r['per_shape_ms']:.1f} | {r['grouped_ms']:.1f} | {r['union_ms']:.1f} | "
                       f"{r['per_shape_over_grouped']:.2f} | {r['per_shape_steps']:.1f} | {r['grouped_steps']:.1f} | "
                       f"{r['union_steps']:.1f} | {fmt(r.get('csg_path_shapes_s'), '.3f')} | "
                       f"{fmt(r.get('csg_path_union_s'), '.3f')} | {fmt(r.get('mesh_path_s'), '.3f')} |")
        out.append("")
    gradient = load("gradient_cost")
    if gradient:
        m = gradient["machine"]
        out += ["## Cost of a gradient iteration", "",
                f"`./run.sh bench gradient_cost.py --mesh{' --accuracy' if gradient.get('accuracy') else ''}"
                f"{' --indirect' if gradient.get('indirect') else ''}` ({m['date']}, `{m['variant']}`): a box minus a sphere, "
                f"the sphere's radius differentiated, {gradient['size']} at {gradient['spp']} spp; one iteration is "
                "a render with the parameter attached plus `dr.backward` of an image loss, against the primal "
                "`csg_path` frame, and Mitsuba's `prb_projective` on the manifold3d mesh (vertex positions "
                "differentiated) where measured.", ""]

        def iteration_table(rows):
            return (["| integrator | s / iteration | x primal |", "|---|---|---|"]
                    + [f"| {r['integrator']} | {r['seconds']:.3f} | {r['ratio']:.1f} |" for r in rows] + [""])
        out += iteration_table(gradient["rows"])
        if gradient.get("accuracy"):
            out += ["Gradient images against finite differences (`--accuracy`, same run, 64x48): a hole cut "
                    "into the top face only (sphere of radius 0.5 at (0.3, -0.2, 0.9)), moved along x, so "
                    "that the mesh's vertices on the sphere and the rim move rigidly with it; forward "
                    "gradients at 256 spp, central differences at 4096 spp (eps 0.02). Mitsuba's "
                    "`prb_projective` samples only the silhouette edges of a mesh (edges with one face "
                    "towards the camera); a hole's rim is a crease whose two faces both face the camera, "
                    "so its motion is missed with face normals (the mesh's own finite difference agrees with "
                    "the model's); with interpolated vertex normals the rim's shading is smoothed, and the "
                    "mesh's image changes otherwise than the model's.",
                    "", "| route | gradient sum | / FD of the model | correlation |", "|---|---|---|---|"]
            for r in gradient["accuracy"]:
                out.append(f"| {r['route']} | {r['sum']:.3f} | {r['ratio']:.3f} | {r['correlation']:.3f} |")
            out.append("")
        if gradient.get("indirect"):
            out += ["Where the derivative is all indirect (`--indirect`, same run and size): a floor lit only by "
                    "a sunlit wall strip above it (the sun travels level with the floor), a dark sphere between "
                    "them out of view, its radius differentiated, max_depth 3. `sppi 0` leaves out "
                    "csg_prb_projective's indirect terms (the curves, and the edges of the sun's shadows, seen "
                    "from the surfaces the camera sees: the scene's rectangles cast edges too); "
                    "Mitsuba's `prb_projective` on the sphere's mesh samples indirect discontinuities "
                    "projectively.", ""]
            out += iteration_table(gradient["indirect"])
    if (common.ROOT / "docs" / "images" / "scaling.png").exists():
        out += ["## Scaling", "", "`./run.sh bench scaling.py`: optimized trace time against primitive count "
                "(640x360) and against image size (Cheese-1000).", "", "![scaling](images/scaling.png)", ""]
    acc = load("accuracy")
    if acc:
        out += ["## Accuracy", "", "See `docs/accuracy.md` (`./run.sh bench accuracy.py`).", ""]
    (common.ROOT / "docs" / "benchmarks.md").write_text("\n".join(out))
    print("wrote docs/benchmarks.md")


if __name__ == "__main__":
    main()
