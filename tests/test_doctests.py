"""The ``>>>`` examples in the package's docstrings run, so they cannot drift from the code."""

import doctest
import importlib
import pathlib
import pkgutil

import pytest

import warpnerf

ROOT = pathlib.Path(warpnerf.__file__).parent


def modules_with_examples() -> list[str]:
    """Dotted names of the warpnerf modules whose source holds a ``>>>`` example (read, not imported)."""
    names = []
    for info in pkgutil.walk_packages([str(ROOT)], prefix="warpnerf."):
        rel = info.name.split(".")[1:]
        path = ROOT.joinpath(*rel, "__init__.py") if info.ispkg else ROOT.joinpath(*rel[:-1], rel[-1] + ".py")
        if path.exists() and ">>> " in path.read_text(encoding="utf-8"):
            names.append(info.name)
    return sorted(names)


MODULES = modules_with_examples()


def test_examples_are_found():
    # the modules documented with examples today; a module losing all of them should be a choice
    for name in ("warpnerf.train.config", "warpnerf.ops.hashgrid", "warpnerf.ops.composite", "warpnerf.model.occupancy"):
        assert name in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    module = importlib.import_module(name)
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS)
    tests = [t for t in finder.find(module, name) if t.examples]
    assert tests, f"{name} mentions '>>> ' but doctest found no example"
    for test in tests:
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.attempted >= len(tests) and result.failed == 0, \
        f"{result.failed} of {result.attempted} examples failed in {name} (output above)"
