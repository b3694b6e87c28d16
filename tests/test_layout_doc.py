"""docs/layout.md lists every module of the package and the plugins: a module missing from
it is a module whose room nobody can find."""
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _rows() -> list[tuple[str, str]]:
    """(first cell, whole row) of every table row of docs/layout.md."""
    rows = []
    for line in (ROOT / "docs" / "layout.md").read_text().splitlines():
        if line.startswith("|") and not set(line) <= set("|- "):
            rows.append((line.split("|")[1], line))
    return rows


def _listed(path: Path, rows) -> bool:
    """Whether a row whose first cell names the module's folder (or a folder above it)
    names the module, as `name`, `name.py` or its whole path."""
    relative = path.relative_to(ROOT).as_posix()
    folders = [parent.relative_to(ROOT).as_posix() + "/" for parent in path.parents if parent != ROOT
               and ROOT in parent.parents]
    name = path.stem
    pattern = re.compile(rf"`({re.escape(name)}|{re.escape(name)}\.py|{re.escape(relative)})`")
    return any(any(folder in first for folder in folders) and pattern.search(row) for first, row in rows)


def test_every_module_is_in_the_layout_doc():
    rows = _rows()
    modules = [p for folder in ("mitsuba_csg", "plugins") for p in sorted((ROOT / folder).rglob("*.py"))
               if p.name != "__init__.py"]
    assert len(modules) > 50
    missing = [p.relative_to(ROOT).as_posix() for p in modules if not _listed(p, rows)]
    assert not missing, f"docs/layout.md does not list: {missing}"


def test_every_package_is_shipped():
    """pyproject.toml lists the packages by name: a new subpackage missing there is left out of
    a wheel (an editable install would not show it)."""
    import tomllib
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(config["packages"])
    found = {init.parent.relative_to(ROOT).as_posix().replace("/", ".")
             for init in (ROOT / "mitsuba_csg").rglob("__init__.py")}
    found |= {"mitsuba_csg.plugins"}         # shipped from the top-level plugins/ folder (package-dir)
    assert found <= listed, f"not in pyproject.toml's packages: {sorted(found - listed)}"
