"""The README's Python example runs as written."""
import re
from pathlib import Path

import numpy as np


def test_readme_python_example_runs():
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    code = re.findall(r"```python\n(.*?)```", text, re.S)[0]
    scope: dict = {}
    exec(compile(code, "README.md", "exec"), scope)
    assert np.all(np.isfinite(scope["hits"].t))
    assert scope["stats"]["height_after"] >= 1
