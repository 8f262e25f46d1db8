"""The embedded demo scene and `mvintrinsic demo`, which must run without Mitsuba."""

from __future__ import annotations

import subprocess
import sys
from datetime import datetime

import numpy as np

from mvintrinsic import load_decomposition, load_scene
from mvintrinsic.cli import DEMO_FRAMES, demo_scene_path
from mvintrinsic.cli import main as cli
from mvintrinsic.io import read_image
from mvintrinsic.relight import relight
from mvintrinsic.sun_position import sun_from_time

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
    # The demo ends with a relit sequence (issue 15): PNG frames and an animated GIF per view.
    from PIL import Image

    for view in scene.views:
        assert len(list((out / "relit" / "frames" / view.stem).glob("frame_*.png"))) == DEMO_FRAMES
        with Image.open(out / "relit" / f"{view.stem}.gif") as gif:
            assert gif.n_frames == DEMO_FRAMES

    # `mvintrinsic relight` on the demo's result: one sun as linear EXR + PNG, equal to relight().
    assert cli(["relight", str(demo_scene_path()), str(out / "result"), str(tmp_path / "one"),
                "--azimuth", "-100", "--elevation", "40", "--quiet"]) == 0
    expected = relight(result, scene, sun=(-100.0, 40.0))
    for view in scene.views:
        image, _ = read_image(tmp_path / "one" / f"{view.stem}.exr")
        np.testing.assert_allclose(image, expected[view.stem], rtol=1e-6, atol=1e-7)
        assert (tmp_path / "one" / f"{view.stem}.png").is_file()
    # --time/--lat/--lon (with --north: the demo's scene.json gives a sun vector, no geography) is the
    # same as --azimuth/--elevation at the solar position of that time and place.
    when, north = "2024-06-21T16:00+02:00", (0.0, 1.0, 0.0)
    assert cli(["relight", str(demo_scene_path()), str(out / "result"), str(tmp_path / "timed"), "--time", when,
                "--lat", "48.85", "--lon", "2.35", "--north", ",".join(map(str, north)), "--quiet"]) == 0
    sun = sun_from_time(datetime.fromisoformat(when), 48.85, 2.35, north=np.array(north), up=scene.up).direction
    expected = relight(result, scene, sun=sun)
    for view in scene.views:
        image, _ = read_image(tmp_path / "timed" / f"{view.stem}.exr")
        np.testing.assert_allclose(image, expected[view.stem], rtol=1e-5, atol=1e-6)
    first, last = (np.asarray(Image.open(out / "relit" / "frames" / scene.views[0].stem / f"frame_{k:03d}.png"),
                              dtype=float) for k in (0, DEMO_FRAMES - 1))
    assert np.abs(first - last).mean() > 1.0  # the shadows and shading moved between the first and last sun


def test_relight_command_refuses_bad_input(tmp_path, capsys):
    demo = str(demo_scene_path())
    # A sun below the horizon is refused before anything is written; so is a folder that is no result.
    assert cli(["relight", demo, str(tmp_path), str(tmp_path / "out"), "--azimuth", "0", "--elevation", "-5"]) == 2
    assert "above the horizon" in capsys.readouterr().err
    assert cli(["relight", demo, str(tmp_path), str(tmp_path / "out"), "--azimuth", "0", "--elevation", "30"]) == 2
    assert "lighting.json" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    assert cli(["relight", demo, str(tmp_path), str(tmp_path / "out"), "--elevation", "30"]) == 2
    assert "--azimuth" in capsys.readouterr().err
    # --time needs a place, and north when scene.json does not say where it is.
    assert cli(["relight", demo, str(tmp_path), str(tmp_path / "out"), "--time", "2024-06-21T16:00+02:00"]) == 2
    assert "--lat" in capsys.readouterr().err
    assert cli(["relight", demo, str(tmp_path), str(tmp_path / "out"), "--time", "2024-06-21T16:00+02:00",
                "--lat", "48.85", "--lon", "2.35"]) == 2
    assert "--north" in capsys.readouterr().err
    assert cli(["relight", demo, str(tmp_path), str(tmp_path / "out"), "--time", "2024-06-21T16:00",
                "--lat", "48.85", "--lon", "2.35", "--north", "0,1,0"]) == 2
    assert "UTC offset" in capsys.readouterr().err
    # Midnight in Paris: the sun is below the horizon.
    assert cli(["relight", demo, str(tmp_path), str(tmp_path / "out"), "--time", "2024-06-21T00:30+02:00",
                "--lat", "48.85", "--lon", "2.35", "--north", "0,1,0"]) == 2
    assert "above the horizon" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
