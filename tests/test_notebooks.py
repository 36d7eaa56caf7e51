"""Every notebook in notebooks/ runs end to end in its small mode, and is stored without outputs.

Execution uses nbclient with kernel "python3". Under the venv that kernel is the venv's own
interpreter (jupyter_client replaces the kernelspec's bare ``python`` with ``sys.executable``);
the test checks this by asking the kernel for ``sys.prefix``, so a stray user-level kernelspec
pointing at another Python fails loudly instead of testing the wrong install.
Measured in fast mode: ~4 s, ~6 s and ~7 s per notebook on the shared two-core machine.

Notebook 4 reads a trained run folder: in fast mode it trains a tiny built-in run itself, and
:func:`test_trained_run_notebook_reads_a_given_run` points it (``WARPNERF_NB_RUN``) at the session's
chair run instead.
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
    assert len(NOTEBOOKS) >= 4, f"expected the three spectrum notebooks and the trained-run one in {NOTEBOOK_DIR}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_stored_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert cell.outputs == [], f"{path.name}: a code cell has outputs; clear them before committing"
            assert cell.execution_count is None, f"{path.name}: a code cell has an execution count"


def _execute(path: Path, monkeypatch, **env: str):
    """Run the notebook (fast mode, no display) in a python3 kernel; returns it with its outputs, after
    checking that the kernel was this interpreter."""
    # the kernel inherits this process's environment: small runs, no display needed
    monkeypatch.setenv("WARPNERF_NB_FAST", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    nb = nbformat.read(path, as_version=4)
    # in memory only: report which Python the kernel is
    nb.cells.append(nbformat.v4.new_code_cell("import sys\nprint(sys.prefix)"))
    client = nbclient.NotebookClient(
        nb, kernel_name="python3", timeout=300, resources={"metadata": {"path": str(NOTEBOOK_DIR)}}
    )
    client.execute()  # raises CellExecutionError on the first failing cell
    printed = _printed(nb.cells[-1]).strip()
    assert printed == sys.prefix, f"kernel python3 runs {printed!r}, not this interpreter's {sys.prefix!r}"
    assert os.path.samefile(printed, sys.prefix)
    return nb


def _printed(cell) -> str:
    return "".join(o.get("text", "") for o in cell.get("outputs", []) if o.get("output_type") == "stream")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs_in_fast_mode(path, monkeypatch, tmp_path):
    monkeypatch.delenv("WARPNERF_NB_RUN", raising=False)  # notebook 4 trains its own tiny run,
    _execute(path, monkeypatch, TMPDIR=str(tmp_path))  # in a temporary folder under pytest's


def test_trained_run_notebook_reads_a_given_run(chair_run, monkeypatch):
    """Notebook 4 on a run folder it did not train: the session's chair run (no G²fR, one test view
    evaluated), so its all-levels render must give the PSNR metrics.json recorded for that view."""
    path = NOTEBOOK_DIR / "04_trained_run_spectra.ipynb"
    nb = _execute(path, monkeypatch, WARPNERF_NB_RUN=str(chair_run))
    said = "".join(_printed(c) for c in nb.cells)
    assert "warpnerf train" not in said, "the notebook trained a run although one was given"
    assert f"reading the run folder {chair_run}" in said
    assert "every level on (no G²fR)" in said
    # the notebook's last check ran (and asserted) rather than saying it does not apply
    assert "in metrics.json" in said and "not comparable with metrics.json" not in said, said[-600:]
