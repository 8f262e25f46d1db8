"""No import of the package, and no decomposition, changes process-wide state (issue 19).

A notebook imports mvintrinsic next to its own code: the core must not swap streams, install
warning filters or logging handlers, change numpy's error handling or global random state, edit
the environment or ``sys.path``, or pick numba's threading layer. The one process-wide action of
the package is documented in ``mvintrinsic/_libusb.py`` (a shared library loaded for open3d when
the system lacks it) and is not observable from Python.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

#: Phase 1: every module the package imports while importing and decomposing (printed as JSON).
DEPENDENCIES = r"""
import json, pkgutil, sys, importlib
import mvintrinsic
for m in pkgutil.walk_packages(mvintrinsic.__path__, "mvintrinsic."):
    if m.name != "mvintrinsic.__main__":
        importlib.import_module(m.name)
from mvintrinsic import Config, decompose, load_scene
from mvintrinsic.cli import demo_scene_path
decompose(load_scene(demo_scene_path()), config=Config.preset("fast"))
print(json.dumps(sorted(n for n in sys.modules if n.split(".")[0] not in ("mvintrinsic", "__main__"))))
"""

#: Phase 2: the third-party and standard modules of phase 1 first (what *they* change on import
#: is theirs: scipy installs warning filters, OpenCV extends LD_LIBRARY_PATH), then the state,
#: then every module of the package, the state, a decomposition, the state.
CHECK = r"""
import importlib, importlib.util, json, logging, os, pkgutil, sys, warnings
# the package's libusb shim, loaded alone (not through the package) so that open3d imports
spec = importlib.util.spec_from_file_location("_shim", os.path.join(sys.argv[2], "_libusb.py"))
shim = importlib.util.module_from_spec(spec); spec.loader.exec_module(shim); shim.ensure_libusb()
for name in json.loads(sys.argv[1]):
    try:
        importlib.import_module(name)
    except Exception:  # private or platform-specific submodules that only load through their parent
        pass
import numpy as np

def state():
    numba = sys.modules.get("numba")
    return {
        "stdout": id(sys.stdout), "stderr": id(sys.stderr), "stdin": id(sys.stdin),
        "warning_filters": repr(warnings.filters),
        "numpy_err": np.geterr(),
        "numpy_random": repr(np.random.get_state()[1][:8].tolist()) + str(np.random.get_state()[2]),
        "environ": dict(os.environ),
        "sys_path": list(sys.path),
        "root_logger": [logging.getLogger().level, [repr(h) for h in logging.getLogger().handlers]],
        "numba_threading_layer": None if numba is None else str(numba.config.THREADING_LAYER),
        "recursion_limit": sys.getrecursionlimit(),
        "cwd": os.getcwd(),
    }

before = state()
import mvintrinsic
# every module but ``python -m mvintrinsic``'s entry point, which runs the command line on import
modules = sorted(m.name for m in pkgutil.walk_packages(mvintrinsic.__path__, "mvintrinsic.")
                 if m.name != "mvintrinsic.__main__")
for name in modules:
    importlib.import_module(name)
after_import = state()
from mvintrinsic import Config, decompose, load_scene
from mvintrinsic.cli import demo_scene_path
result = decompose(load_scene(demo_scene_path()), config=Config.preset("fast"))
after_decompose = state()
print(json.dumps({"modules": modules, "before": before, "after_import": after_import,
                  "after_decompose": after_decompose, "views": len(result.stems),
                  "jit": sorted({m.split(".")[0] for m in sys.modules} & {"numba", "llvmlite", "pymatting"})}))
"""


def test_importing_every_module_and_decomposing_leaves_the_process_alone():
    import mvintrinsic

    first = subprocess.run([sys.executable, "-c", DEPENDENCIES], capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-3000:]
    dependencies = first.stdout.strip().splitlines()[-1]
    package = os.path.dirname(mvintrinsic.__file__)
    done = subprocess.run([sys.executable, "-c", CHECK, dependencies, package], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert len(report["modules"]) >= 20, report["modules"]  # every module of the package was imported
    assert report["views"] > 0
    assert report["jit"] == []  # no numba, llvmlite or pymatting loaded by the core
    for stage in ("after_import", "after_decompose"):
        changed = {k: (report["before"][k], report[stage][k]) for k in report["before"]
                   if report["before"][k] != report[stage][k]}
        assert not changed, f"{stage}: process-wide state changed: {changed}"


#: colour-science, imported without matplotlib, puts MagicMock stand-ins into ``sys.modules``;
#: matplotlib is blocked here (``None`` in ``sys.modules``) so the check runs whether or not it is installed.
WITHOUT_MATPLOTLIB = r"""
import json, sys
for name in ("matplotlib", "matplotlib.pyplot", "cycler", "mpl_toolkits"):
    sys.modules[name] = None
from mvintrinsic.files import import_colour
colour = import_colour()
encoded = float(colour.cctf_encoding(0.5, function="sRGB"))
try:
    import matplotlib.pyplot
    outcome = "imported " + repr(matplotlib.pyplot)
except ImportError:
    outcome = "ImportError"
stand_ins = sorted(n for n, m in sys.modules.items() if type(m).__module__ == "unittest.mock")
print(json.dumps({"encoded": encoded, "import_matplotlib": outcome, "stand_ins": stand_ins}))
"""


def test_importing_colour_without_matplotlib_leaves_no_stand_in_matplotlib():
    # A later ``import matplotlib`` (a benchmark's figure, the user's notebook) must fail as
    # matplotlib is absent, not hand back colour's MagicMock that draws nothing (CI failure of
    # test_relight_occluder_distance_figure_is_drawn in a venv without the plot extra).
    done = subprocess.run([sys.executable, "-c", WITHOUT_MATPLOTLIB], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["import_matplotlib"] == "ImportError"
    assert report["stand_ins"] == []
    assert abs(report["encoded"] - 0.7353569830524495) < 1e-9  # sRGB encoding of 0.5: colour still works
