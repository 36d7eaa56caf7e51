"""Every notebook in notebooks/ runs end to end in its small mode, and is stored without outputs.

Execution uses nbclient with kernel "python3". Under the venv that kernel is the venv's own
interpreter (jupyter_client replaces the kernelspec's bare ``python`` with ``sys.executable``);
the test checks this by asking the kernel for ``sys.prefix``, so a stray user-level kernelspec
pointing at another Python fails loudly instead of testing the wrong install.
Measured in fast mode: ~4 s, ~6 s and ~7 s per notebook on the shared two-core machine.
"""

import os
import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOK_DIR = Path(__file__).resolve().parent.parent / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 3, f"expected the three spectrum notebooks in {NOTEBOOK_DIR}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_stored_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert cell.outputs == [], f"{path.name}: a code cell has outputs; clear them before committing"
            assert cell.execution_count is None, f"{path.name}: a code cell has an execution count"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs_in_fast_mode(path, monkeypatch):
    # the kernel inherits this process's environment: small runs, no display needed
    monkeypatch.setenv("WARPNERF_NB_FAST", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(path, as_version=4)
    # in memory only: report which Python the kernel is
    nb.cells.append(nbformat.v4.new_code_cell("import sys\nprint(sys.prefix)"))
    client = nbclient.NotebookClient(
        nb, kernel_name="python3", timeout=300, resources={"metadata": {"path": str(NOTEBOOK_DIR)}}
    )
    client.execute()  # raises CellExecutionError on the first failing cell
    printed = "".join(o.get("text", "") for o in nb.cells[-1].outputs if o.get("output_type") == "stream").strip()
    assert printed == sys.prefix, f"kernel python3 runs {printed!r}, not this interpreter's {sys.prefix!r}"
    assert os.path.samefile(printed, sys.prefix)
