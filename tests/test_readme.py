"""The README's Python examples run as written."""

import re
from pathlib import Path

import numpy as np


def test_readme_examples_run():
    text = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) >= 2
    namespace: dict = {}
    exec(compile("\n".join(blocks), "README.md", "exec"), namespace)
    assert namespace["u0"].shape == (4,)
    assert np.all(np.isfinite(np.asarray(namespace["info"].nominal_trajectory)))
