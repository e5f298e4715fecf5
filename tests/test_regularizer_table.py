import math

from meshmei.cli import main
from meshmei.regularizer_table import tabulate_regularizers
from meshmei.regularizers import REGULARIZERS


def test_demo_table_is_finite_and_rest_poses_are_arap_minima():
    lines = []
    rows = tabulate_regularizers(n_vertices=300, out=lines.append)
    assert len(rows) == 3 * 2 * len(REGULARIZERS)
    assert all(math.isfinite(v) for v, _ in rows.values())
    for kind in ("sheet", "sphere", "torus"):
        # the rest pose is its own ARAP optimum; the bump moves every vertex set away from it
        assert rows[(kind, "rest", "arap (Sorkine-Alexa)")][0] < 1e-9 * rows[(kind, "bumped", "arap (Sorkine-Alexa)")][0]
        assert rows[(kind, "rest", "arap (direction)")][0] < 1e-9 * rows[(kind, "bumped", "arap (direction)")][0]
    assert any(line.startswith("arap (Sorkine-Alexa)") for line in lines)


def test_cli_regularizers_exit_code(capsys):
    assert main(["regularizers", "--n-vertices", "200"]) == 0
    assert "all 36 values finite: True" in capsys.readouterr().out
