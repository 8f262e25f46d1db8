"""The embedded demo scene and `mvintrinsic demo`, which must run without Mitsuba."""

from __future__ import annotations

import subprocess
import sys

from mvintrinsic import load_decomposition, load_scene
from mvintrinsic.cli import demo_scene_path
from mvintrinsic.io import read_image

DEMO_MAX_BYTES = 10 * 1024 * 1024  # issue 3: the embedded demo is at most 10 MB


def test_demo_scene_is_small_and_complete():
    folder = demo_scene_path()
    size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    assert size <= DEMO_MAX_BYTES, f"demo scene is {size / 2**20:.1f} MB"
    scene = load_scene(folder)
    assert len(scene.views) >= 4
    for name in ("reflectance", "shading", "sun_shading", "env_shading", "sun_visibility", "sky_mask"):
        assert len(list((folder / "gt" / name).iterdir())) == len(scene.views), name
    assert (folder / "gt" / "lighting.json").is_file()


def test_demo_command_runs_without_mitsuba(tmp_path):
    out = tmp_path / "demo"
    code = (
        "import sys; sys.modules['mitsuba'] = None\n"  # any import of mitsuba now fails
        "from mvintrinsic.cli import main\n"
        f"sys.exit(main(['demo', '--out', {str(out)!r}]))\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    for word in ("views", "L_sun", "compare", "previews", "scores"):
        assert word in run.stdout, word
    scene = load_scene(demo_scene_path())
    views = len(scene.views)
    result = load_decomposition(out / "result")
    assert result.stems == tuple(v.stem for v in scene.views)
    assert len(list((out / "compare").glob("*.png"))) == views
    tile, _ = read_image(out / "compare" / f"{scene.views[0].stem}.png")
    assert tile.shape[:2] == (2 * scene.views[0].shape[0], 5 * scene.views[0].shape[1])  # estimate over truth
    for name in ("image", "reflectance", "shading", "sun_shading", "env_shading", "sun_visibility"):
        assert len(list((out / "ground_truth" / name).glob("*.png"))) == views, name
