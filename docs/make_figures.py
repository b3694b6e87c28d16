"""Draw the figures of docs/algorithm.md: the automaton and an optimized tree's heights.

    ./run.sh -- python docs/make_figures.py
"""
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

HERE = Path(__file__).resolve().parent


def automaton():
    fig, ax = plt.subplots(figsize=(9, 4.6))
    ax.set_xlim(0, 10)
    ax.set_ylim(0, 5.6)
    ax.axis("off")
    boxes = {
        "GOTO": (1.8, 3.8, "GoTo\n(child from t_start:\nbox test, leaf hit,\nor descend + push)"),
        "CLASSIFY": (5.2, 3.8, "Classify\n(state table of the node:\nreturn L/R, loop L/R, miss)"),
        "RETURN": (8.4, 3.8, "Return\n(pop the frame:\nSAVE_L / LOAD_L / LOAD_R)"),
        "DONE": (8.4, 0.9, "Done\n(hit of the root)"),
    }
    for key, (x, y, text) in boxes.items():
        ax.add_patch(FancyBboxPatch((x - 1.35, y - 0.75), 2.7, 1.5, boxstyle="round,pad=0.05",
                                    fc="#f3e6c4" if key != "DONE" else "#dfe8f3", ec="#555"))
        ax.text(x, y, text, ha="center", va="center", fontsize=8.5)

    def arrow(a, b, text, rad=0.0, dy=0.0):
        (x1, y1), (x2, y2) = a, b
        ax.add_patch(FancyArrowPatch((x1, y1), (x2, y2), connectionstyle=f"arc3,rad={rad}", arrowstyle="-|>",
                                     mutation_scale=12, color="#333"))
        ax.text((x1 + x2) / 2, (y1 + y2) / 2 + dy, text, ha="center", va="center", fontsize=7.5, color="#333",
                bbox=dict(fc="white", ec="none", pad=0.5))

    arrow((3.15, 4.1), (3.85, 4.1), "both hits\nknown", dy=0.45)
    arrow((6.55, 4.1), (7.05, 4.1), "return", dy=0.35)
    arrow((5.0, 3.05), (2.2, 3.05), "loop L / R:\nt_start = t", rad=-0.35, dy=-0.75)
    arrow((8.0, 4.55), (2.2, 4.55), "SAVE_L popped: go right", rad=0.25, dy=1.05)
    arrow((8.9, 4.55), (6.0, 4.55), "LOAD_L / LOAD_R popped", rad=0.35, dy=0.75)
    arrow((8.4, 3.05), (8.4, 1.65), "stack empty", dy=0.0)
    ax.text(1.2, 2.1, "descend into an operation child:\npush t_start or the other hit and a frame,\n"
            "stay in GoTo for the child's children", ha="center", fontsize=7.5, color="#333")
    ax.text(5.0, 0.55, "One loop iteration runs GoTo, then Classify, then Return, each masked per lane.\n"
            "Hit stack: (t, leaf, info); state stack: frames. Both share one stack pointer.",
            ha="center", fontsize=8, color="#333")
    fig.tight_layout()
    fig.savefig(HERE / "images" / "automaton.png", dpi=110)


def heights():
    import mitsuba_csg as csg
    from mitsuba_csg.scenes import cheese, sphere_chain
    box, *holes = cheese(1000).children
    chain = box
    for hole in holes:                 # the Cheese as a user might write it: a - b - c - ...
        chain = chain - hole
    names, before, after = [], [], []
    for name, model in [("union of 10k spheres\n(s0 | s1) | s2 ...", sphere_chain(10000)),
                        ("Cheese-1000\n((box - s1) - s2) ...", chain)]:
        _, stats = csg.optimize(model)
        names.append(name)
        before.append(stats["height_input"])
        after.append(stats["height_after"])
    fig, ax = plt.subplots(figsize=(6, 3))
    xs = range(len(names))
    ax.bar([x - 0.2 for x in xs], before, 0.4, label="as written")
    ax.bar([x + 0.2 for x in xs], after, 0.4, label="optimized")
    ax.set_yscale("log")
    ax.set_xticks(list(xs), names)
    ax.set_ylabel("tree height (operation levels)")
    for x, b, a in zip(xs, before, after):
        ax.text(x - 0.2, b, str(b), ha="center", va="bottom", fontsize=8)
        ax.text(x + 0.2, a, str(a), ha="center", va="bottom", fontsize=8)
    ax.legend()
    fig.tight_layout()
    fig.savefig(HERE / "images" / "heights.png", dpi=110)


if __name__ == "__main__":
    automaton()
    heights()
