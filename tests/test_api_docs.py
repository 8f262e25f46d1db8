"""The API reference (docs/api) builds from the numpydoc docstrings without a warning (issue 19)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_api_reference_builds_warning_free(tmp_path):
    pytest.importorskip("sphinx", reason="sphinx is not installed (pip install -e '.[docs]')")
    pytest.importorskip("numpydoc", reason="numpydoc is not installed (pip install -e '.[docs]')")
    # autosummary writes its stub pages beside the sources: build from a copy of docs/api
    source = tmp_path / "api"
    source.mkdir()
    for name in ("conf.py", "index.rst"):
        (source / name).write_text((ROOT / "docs" / "api" / name).read_text(encoding="utf-8"), encoding="utf-8")
    done = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(source),
                           str(tmp_path / "html")], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-5000:]
    pages = {p.name for p in (tmp_path / "html" / "generated").glob("*.html")}
    for module in ("mvintrinsic.relight", "mvintrinsic.env_refine", "mvintrinsic.pipeline", "mvintrinsic.skymodel"):
        assert f"{module}.html" in pages, module
    relight = (tmp_path / "html" / "generated" / "mvintrinsic.relight.html").read_text(encoding="utf-8")
    assert "Relighter" in relight and "RelightConfig" in relight  # the members are documented
