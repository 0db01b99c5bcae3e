"""The notebooks (``notebooks/*.py``, Jupytext percent scripts paired with ``.ipynb``): the
pairs are in sync (fast), and every notebook runs top to bottom in a fresh Jupyter kernel
of this interpreter, followed by a hidden cell of checks on its results (slow)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

jupytext = pytest.importorskip("jupytext")
nbformat = pytest.importorskip("nbformat")

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
SCRIPTS = sorted(NOTEBOOKS.glob("*.py"))

# checks appended to each notebook before it runs (the notebooks stay free of test code)
CHECKS = {
    "quickstart": """
assert track.shape == (59, 3) and np.all(np.isfinite(track))
assert err.mean() < 0.2, err.mean()
assert {p.name for p in out.iterdir()} == {"intel_decay_rate.npz", "intel_track.tum"}
assert np.loadtxt(out / "intel_track.tum").shape == (59, 8)
""",
    "gradients": """
assert float(jnp.max(jnp.abs(g_closed.sum(0) - g_auto))) < 1e-9
assert float(jnp.max(jnp.abs(h_closed.sum(0) - h_auto))) < 1e-8
assert float(jnp.max(jnp.abs(h_paper.sum(0) - h_auto))) > 1e-6
np.testing.assert_allclose(np.asarray(testing.manifold_jacobian(obj, pose)),
                           np.asarray(testing.manifold_finite_difference(obj, pose)),
                           rtol=1e-5, atol=1e-6)
""",
    "dct_and_fields": """
assert float(ll_dct.mean()) > float(maps.field_log_likelihood(grid, patch).mean())
assert np.linalg.norm(np.asarray(matched.translation()) - log.poses[s, :2]) < 0.05
""",
    "polylines": """
by = {(J, name): rmse for J, name, rmse, f in rows}
assert all(by[J, "PLE+"] <= by[J, "PLE"] + 1e-9 for J in (10, 20, 30))
assert by[30, "PLE"] < by[10, "PLE"]
""",
    "planes": """
assert hv.n_gt == 12 and hv.n_correct >= 10
assert hv_room.f > 0.736 and hv_room.k > 0.779  # the paper's Table 11.1
""",
    "poles": """
assert len(pole_map) >= 5 and np.median(d) < 0.2
ll = np.asarray(model(guesses, (near, np.ones(len(near), bool))))
assert ll[0] > ll[1] and ll[0] > ll[2]
""",
}


def test_every_notebook_is_paired_and_in_sync():
    assert {p.stem for p in SCRIPTS} == set(CHECKS)
    for script in SCRIPTS:
        ipynb = script.with_suffix(".ipynb")
        assert ipynb.exists(), f"{ipynb.name} missing: run `make notebooks`"
        a = jupytext.read(script)
        b = nbformat.read(ipynb, as_version=4)
        cells_a = [(c.cell_type, c.source.strip()) for c in a.cells]
        cells_b = [(c.cell_type, c.source.strip()) for c in b.cells]
        assert cells_a == cells_b, f"{script.name} and {ipynb.name} differ: run `make notebooks`"
        # stored without outputs (reviewable diffs; outputs come from running them)
        assert all(not c.get("outputs") for c in b.cells if c.cell_type == "code"), ipynb.name


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CHECKS))
def test_notebook_runs(name, tmp_path):
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    nb = jupytext.read(NOTEBOOKS / f"{name}.py")
    nb.cells.append(nbformat.v4.new_code_cell(CHECKS[name]))
    # a kernel spec of this interpreter (not whatever "python3" means on the machine)
    spec = tmp_path / "kernels" / "lidarjax-test"
    spec.mkdir(parents=True)
    argv = [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"]
    (spec / "kernel.json").write_text(
        json.dumps({"argv": argv, "display_name": "lidarjax test", "language": "python"})
    )
    env = {"JUPYTER_PATH": str(tmp_path), "MPLBACKEND": "Agg"}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        client = nbclient.NotebookClient(
            nb,
            kernel_name="lidarjax-test",
            timeout=900,
            resources={"metadata": {"path": str(NOTEBOOKS)}},
        )
        client.execute()
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
