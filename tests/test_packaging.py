"""Every third-party module the package imports is a declared core dependency.

`pip install .` (the README's first command) installs only the core dependencies; a module that
only the test extras bring in (matplotlib was one) makes `warpnerf train` fail on a user's machine.
"""

import ast
import pathlib
import re
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
# import name -> distribution name, where they differ
DIST = {"warp": "warp-lang", "PIL": "pillow", "mpl_toolkits": "matplotlib", "tomli": "tomli", "skimage": "scikit-image",
        "imageio_ffmpeg": "imageio-ffmpeg", "tomli_w": "tomli-w"}
OPTIONAL = {"lpips", "pycolmap"}  # lpips: imported inside try/except, used only when its weights are present;
# pycolmap: the "colmap" extra, imported only by `warpnerf process` (clear error when absent)

tomllib = pytest.importorskip("tomllib") if sys.version_info >= (3, 11) else pytest.importorskip("tomli")


def imported_top_level_modules() -> set[str]:
    names = set()
    for path in [*ROOT.joinpath("warpnerf").rglob("*.py"), *ROOT.joinpath("kernels").rglob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return names


def test_third_party_imports_are_core_dependencies():
    project = tomllib.loads(ROOT.joinpath("pyproject.toml").read_text())["project"]
    name = lambda d: re.split(r"[<>=!~;\[ ]", d, maxsplit=1)[0].strip().lower()  # noqa: E731
    declared = {name(d) for d in project["dependencies"]}
    # optional features (render's MP4, export, viewer, ...) import their extra's packages lazily, with a
    # one-line "pip install 'warpnerf[extra]'" error; the test extra does not count (users never get it)
    extras = {name(d) for key, deps in project["optional-dependencies"].items() if key != "test" for d in deps}
    third_party = imported_top_level_modules() - set(sys.stdlib_module_names) - {"warpnerf", "__future__"} - OPTIONAL
    missing = sorted(m for m in third_party if DIST.get(m, m).lower() not in declared | extras)
    assert not missing, f"imported but not in [project] dependencies or a feature extra: {missing}"
    assert {"warp-lang", "torch", "numpy", "imageio", "matplotlib"} <= declared
