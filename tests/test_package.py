"""Packaging: open3d imports on a system without libusb, the layer structure, the CLI."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

import mvintrinsic
from mvintrinsic.cli import main

PACKAGE = Path(mvintrinsic.__file__).parent

# Bottom to top. A core module may import only modules listed before it; the edge may import the
# core, and the core never imports the edge (docs/architecture.md).
CORE_LAYERS = [
    "_version", "_validation", "_cluster", "_libusb", "camera", "scene", "results", "image_model", "envmap", "skymodel", "environment", "planes", "raytrace", "stereo", "env_shading",
    "sun_position", "exposure", "pixels", "resolution", "correspondence", "photo_occupancy", "sun_calibration", "segmentation", "shadow_mrf",
    "multiview_shadows", "laplacian", "matting", "env_refine", "occluders", "model_choice", "shadow_clusters", "caster", "shadow_caster", "relit_shading", "relight",
    "pipeline",
]
EDGE = {"io", "files", "result_folder", "errors", "metrics", "cli", "__main__", "evaluation", "preview", "__init__"}


def system_has_libusb() -> bool:
    """Whether the dynamic linker finds libusb by itself (asked in a process mvintrinsic never ran in)."""
    code = "import ctypes; ctypes.CDLL('libusb-1.0.so.0')"
    return subprocess.run([sys.executable, "-c", code], capture_output=True).returncode == 0


def test_import_open3d_after_mvintrinsic_in_a_fresh_interpreter():
    code = "import mvintrinsic, open3d, mvintrinsic._libusb as u; print(open3d.__version__); print(u._loaded)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0].count(".") >= 2
    if sys.platform.startswith("linux") and not system_has_libusb():
        # The bundled copy was needed and used.
        assert out[1].endswith((".so", ".so.0")) and "libusb_package" in out[1]
    else:
        assert out[1] == "None"  # the system's own library is left alone


def test_every_module_is_in_a_layer():
    modules = {p.stem for p in PACKAGE.glob("*.py")}
    assert modules == set(CORE_LAYERS) | EDGE


@pytest.mark.parametrize("module", CORE_LAYERS)
def test_core_imports_only_lower_layers(module):
    tree = ast.parse((PACKAGE / f"{module}.py").read_text())
    allowed = set(CORE_LAYERS[: CORE_LAYERS.index(module)])
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            targets = [node.module] if node.module else [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mvintrinsic"):
            targets = [node.module.split(".")[1]] if "." in node.module else [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            targets = [a.name.split(".")[1] for a in node.names if a.name.startswith("mvintrinsic.")]
        else:
            continue
        for target in targets:
            assert target.split(".")[0] in allowed, f"{module} imports {target}"


def test_cli_info_on_a_scene(scene_dir, capsys):
    assert main(["info", str(scene_dir), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["views"] == 2 and summary["image_sizes"] == {"64x48": 2}
    assert summary["proxy"]["kind"] == "mesh" and summary["ground_truth"] == {}
    assert summary["sun"]["elevation_deg"] == pytest.approx(57.99, abs=0.01)  # asin(0.8 / |(0.4, -0.3, 0.8)|)
    assert summary["sun"]["azimuth_deg"] == pytest.approx(-36.87, abs=0.01)  # atan2(-0.3, 0.4)
    assert main(["info", str(scene_dir)]) == 0
    assert "2  (2 x 64x48)" in capsys.readouterr().out


def test_cli_reports_bad_input_on_one_line(tmp_path, capsys):
    assert main(["info", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "missing" in err and "scene folder not found" in err


def test_console_script_is_installed():
    bin_dir = Path(sys.executable).parent
    script = bin_dir / "mvintrinsic"
    if not script.exists():
        pytest.skip("package not installed in this interpreter's environment (pip install -e .)")
    out = subprocess.run([str(script), "--version"], capture_output=True, text=True, check=True).stdout
    assert out.strip() == f"mvintrinsic {mvintrinsic.__version__}"


def test_license_and_citation_match_the_package():
    """LICENSE is the licence pyproject declares; CITATION.cff cites this version and the paper."""
    import re

    root = Path(__file__).resolve().parents[1]
    declared = re.search(r'^license = \{ text = "([^"]+)" \}$', (root / "pyproject.toml").read_text(), re.M).group(1)
    assert declared == "BSD-3-Clause"
    assert (root / "LICENSE").read_text().startswith("BSD 3-Clause License")
    citation = (root / "CITATION.cff").read_text(encoding="utf-8")
    assert re.search(r"^version: (\S+)$", citation, re.M).group(1) == mvintrinsic.__version__
    assert re.search(r"^license: (\S+)$", citation, re.M).group(1) == declared
    assert "doi: 10.1145/2756549" in citation  # Duchêne et al. 2015, the method


#: Issue 19: a module a reader can hold in mind; split by job above this.
MAX_MODULE_LINES = 900


def test_no_module_is_longer_than_the_limit():
    lengths = {str(p.relative_to(PACKAGE)): len(p.read_text(encoding="utf-8").splitlines())
               for p in PACKAGE.rglob("*.py")}
    assert not {k: n for k, n in lengths.items() if n > MAX_MODULE_LINES}
