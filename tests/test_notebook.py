"""examples/ctr_episode.ipynb runs headless, start to end, in a Jupyter kernel."""

import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "examples" / "ctr_episode.ipynb"


@pytest.mark.slow
def test_the_example_notebook_runs_an_episode_and_plots_the_predicted_distance(
        tmp_path, monkeypatch):
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(NOTEBOOK, as_version=4)
    params = nb.cells[1]
    assert params.source.startswith("# Parameters")
    # A short headless run: as fast as possible, 3 simulated seconds.
    params.source = re.sub(r"REALTIME_RATE = [0-9.]+", "REALTIME_RATE = 0.0", params.source)
    params.source = re.sub(r"MAX_SIM_TIME_S = [0-9.]+", "MAX_SIM_TIME_S = 3.0", params.source)
    # A kernel of this interpreter, whatever kernels the machine has installed.
    spec = tmp_path / "kernels" / "drake-grasp-test"
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "drake-grasp test", "language": "python"}))
    monkeypatch.setenv("JUPYTER_PATH", str(tmp_path))
    NotebookClient(nb, kernel_name="drake-grasp-test", timeout=600,
                   resources={"metadata": {"path": str(NOTEBOOK.parent)}}).execute()

    def text(cell):
        return "".join(o.get("text", "") for o in cell.get("outputs", []))

    outputs = "".join(text(c) for c in nb.cells if c.cell_type == "code")
    assert "http://" in outputs  # Meshcat's URL
    steps = int(re.search(r"(\d+) control steps", outputs).group(1))
    assert steps >= 5  # 3 s at the controller's 0.1 s period, after the start
    plots = [o for o in nb.cells[-1].outputs if "image/png" in o.get("data", {})]
    assert len(plots) == 1
