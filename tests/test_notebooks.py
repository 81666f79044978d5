"""Execute the tutorial notebooks (at toy sizes: EVHSI_NB_SMALL=1) so they never rot.

The kernel is `python3` from the running interpreter's environment (jupyter_client
starts it with `sys.executable`), so `make test` uses the venv's evhsi_jax.
"""

import os
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


def test_notebooks_found():
    assert [p.name[:2] for p in NOTEBOOKS] == ["01", "02", "03"]


# The optical-design notebook compiles the design gradients (~85 s with an empty cache):
# it runs with `-m slow` (`make bench`) to keep `make test` inside its 10 minutes; the
# design's gradients themselves are checked in tests/design/test_design.py every run.
_CASES = [
    pytest.param(p, marks=pytest.mark.slow) if p.stem.startswith("03") else p
    for p in NOTEBOOKS
]


@pytest.mark.parametrize("path", _CASES, ids=lambda p: p.stem)
def test_notebook_runs(path, monkeypatch):
    monkeypatch.setenv("EVHSI_NB_SMALL", "1")
    # Warnings are errors in this suite; in the kernel they only print.
    monkeypatch.setenv("PYTHONWARNINGS", "default")
    nb = nbformat.read(path, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), (
        "commit notebooks without outputs"
    )
    client = nbclient.NotebookClient(
        nb,
        timeout=600,
        kernel_name="python3",
        resources={"metadata": {"path": str(path.parent)}},
    )
    client.execute()
    errors = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
        if o.get("output_type") == "error"
    ]
    assert not errors
    # Every code cell ran and printed/plotted something or defined names.
    assert all(c.get("execution_count") for c in nb.cells if c.cell_type == "code")
    assert os.environ["EVHSI_NB_SMALL"] == "1"
