"""The README's Python example must run as printed."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], str(README), "exec"), namespace)
    res, rigid = namespace["res"], namespace["rigid"]
    assert int(res.status) == 0
    scene = namespace["scene"]
    assert np.mean(np.linalg.norm(np.asarray(res.points - scene.points), axis=1)) < 3e-3
    assert namespace["R_w_o"].shape == (rigid.times.shape[0], 3, 3)
    err = np.linalg.norm(np.asarray(namespace["p_w_o"] - rigid.p_w_o), axis=1)
    assert err.mean() < 5e-3
