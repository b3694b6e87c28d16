"""Write docs/plugins.md from the plugins' docstrings (the docstring is the documentation).

    ./run.sh -- python docs/make_plugin_docs.py
"""
import inspect
import re
from pathlib import Path

import mitsuba_csg  # noqa: F401  (registers the plugins, selects a variant)
from mitsuba_csg.plugins import csg_shape, registry

HERE = Path(__file__).resolve().parent


def to_markdown(doc: str) -> str:
    doc = inspect.cleandoc(doc)
    out, lines, i = [], doc.splitlines(), 0
    while i < len(lines):
        line = lines[i]
        if line.startswith(".. _"):
            i += 1
            continue
        if i + 1 < len(lines) and set(lines[i + 1].strip()) == {"-"} and line.strip():
            out.append("## " + line.strip().replace(":monosp:`", "`"))
            i += 2
            continue
        if line.strip() == ".. pluginparameters::":
            out += ["", "| parameter | type | meaning |", "|---|---|---|"]
            i += 1
            rows = []
            while i < len(lines) and (not lines[i].strip() or lines[i].startswith(" ")):
                text = lines[i].strip()
                if text.startswith("* - "):
                    rows.append([text[4:]])
                elif text.startswith("- ") and rows:
                    rows[-1].append(text[2:])
                elif text and rows:
                    rows[-1][-1] += " " + text
                i += 1
            for row in rows:
                row += [""] * (3 - len(row))
                out.append("| " + " | ".join(re.sub(r"\|(\w+)\|", r"\1", c) for c in row[:3]) + " |")
            out.append("")
            continue
        if line.strip() == ".. code-block:: python":
            out.append("```python")
            i += 1
            while i < len(lines) and not lines[i].strip():
                i += 1
            while i < len(lines) and (not lines[i].strip() or lines[i].startswith(" ")):
                out.append(lines[i][4:])
                i += 1
            while out[-1] == "":
                out.pop()
            out.append("```")
            continue
        out.append(line.replace(":monosp:`", "`"))
        i += 1
    return "\n".join(out)


def main():
    parts = ["# Mitsuba plugins", "",
             "Generated from the plugins' docstrings by `docs/make_plugin_docs.py`. `import mitsuba_csg` "
             "registers them for the current variant (call `mitsuba_csg.register_plugins()` after switching); every "
             "JIT variant works, RGB, mono and spectral (`llvm_*` on any CPU, `cuda_*` on NVIDIA GPUs).", ""]
    classes = [csg_shape.CSGShape] + [registry.integrator_class(name) for name in registry.integrator_names()]
    for cls in classes:
        parts += [to_markdown(cls.__doc__), ""]
    (HERE / "plugins.md").write_text("\n".join(parts))


if __name__ == "__main__":
    main()
