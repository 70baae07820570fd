"""`fracto --help` (and each verb's --help) answers without the numeric stack: the CLI imports
OpenCV, SciPy, numba and matplotlib only inside the verbs that run work."""

import json
import subprocess
import sys

import pytest

HEAVY = ("cv2", "scipy", "numba", "matplotlib", "trimesh", "aiohttp", "tifffile")


@pytest.mark.parametrize("arguments", [["--help"], ["height", "--help"], ["roughness", "--help"], ["demo", "--help"]])
def test_help_imports_no_numeric_stack(arguments):
    probe = (
        "import json, sys\nfrom fractoscope.cli.main import main\ntry:\n    main(sys.argv[1:])\n"
        "except SystemExit as done:\n    code = done.code\n"
        "print(json.dumps([code, sorted({name.split('.')[0] for name in sys.modules})]))"
    )
    done = subprocess.run([sys.executable, "-c", probe, *arguments], capture_output=True, text=True, timeout=120)
    code, loaded = json.loads(done.stdout.splitlines()[-1])
    assert code == 0, done.stderr
    assert "fractoscope" in loaded and set(loaded).isdisjoint(HEAVY), sorted(set(loaded) & set(HEAVY))


def test_a_verb_that_needs_the_services_says_how_to_install_them(tmp_path):
    """Without the services distribution (simulated by hiding its packages), a local verb ends
    with one line that names the extra to install, not a traceback."""
    probe = (
        "import sys, importlib.abc\n"
        "class Hide(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        if name.split('.')[:2] in (['fractoscope', 'stereo'], ['fractoscope', 'formats'], "
        "['fractoscope', 'server'], ['fractoscope', 'sem']):\n"
        "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n"
        "sys.meta_path.insert(0, Hide())\n"
        "from fractoscope.cli.main import main\nmain(sys.argv[1:])\n"
    )
    heights = tmp_path / "h.npz"
    heights.write_bytes(b"")
    done = subprocess.run(
        [sys.executable, "-c", probe, "mesh", str(heights), "-o", str(tmp_path / "tiles")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        "error: fracto mesh works on this machine and needs the services installed: "
        "pip install 'fractoscope-cli[local]'"
    ]
