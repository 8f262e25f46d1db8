"""The README's "Use from Python" blocks run as written, with exported names only (issue 19)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest

import mvintrinsic

README = Path(__file__).resolve().parents[1] / "README.md"


def python_blocks() -> list[str]:
    text = README.read_text(encoding="utf-8")
    section = text.split("## Use from Python", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_readme_blocks_use_exported_names_only():
    blocks = python_blocks()
    assert len(blocks) == 2
    used = {node.attr for block in blocks for node in ast.walk(ast.parse(block))
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "mvi"}
    assert used <= set(mvintrinsic.__all__), used - set(mvintrinsic.__all__)
    assert not [line for block in blocks for line in block.splitlines() if re.match(r"\s*from mvintrinsic", line)]


def test_package_attributes_do_not_hide_its_modules():
    """``import mvintrinsic.X as m`` gives the module X: no exported name shadows a module."""
    import pkgutil

    modules = {m.name for m in pkgutil.iter_modules(mvintrinsic.__path__)}
    assert not modules & set(mvintrinsic.__all__), modules & set(mvintrinsic.__all__)


def test_readme_blocks_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the first block saves a result folder in the working directory
    namespace: dict = {}
    for block in python_blocks():
        exec(compile(block, str(README), "exec"), namespace)  # noqa: S102 - the README's own code
    scene = namespace["scene"]
    first = scene.views[0].stem
    # block 1: the result folder it saved reads back with every view
    assert mvintrinsic.load_decomposition(tmp_path / "result").stems == scene.stems
    # block 2: the view's own labels are the ones its layers carry through Step 4
    own, valid = namespace["labels"], namespace["own"].valid
    np.testing.assert_array_equal(namespace["layers"][first].shadow_labels[valid], own[valid])
    # ... and every view is relit, differently for different suns
    assert set(namespace["images"]) == set(scene.stems)
    for image in namespace["images"].values():
        assert np.isfinite(image).all() and image.min() >= 0
    frames = namespace["frames"]
    assert len(frames) == 2 and not np.allclose(frames[0][first], frames[1][first])


def test_example_composes_the_stages(tmp_path):
    """examples/compose_stages.py (the README's composition as a script) runs on the demo."""
    import runpy
    import sys

    script = README.parent / "examples" / "compose_stages.py"
    argv = sys.argv
    sys.argv = [str(script), "--out", str(tmp_path)]
    try:
        with pytest.raises(SystemExit) as done:
            runpy.run_path(str(script), run_name="__main__")
    finally:
        sys.argv = argv
    assert done.value.code == 0
    assert sorted(p.name for p in tmp_path.glob("*.png")) == [
        "view_000_reflectance.png", "view_000_relit.png", "view_000_shading.png"]
