"""The CSV tables (``--csv``, the app's downloads): plain CSV that pandas and a spreadsheet
read as they are, safe to open (no cell runs as a formula), numbers kept as numbers, the
provenance in a JSON sidecar, and an NROY table of a sensible size (issue 40 item 8,
issue 41 item 7)."""

from __future__ import annotations

import csv
import io
import json
import textwrap

import numpy as np
import pandas as pd
import scipy.stats
from test_own_simulators import CSV, SIMULATOR, case_toml

from mdcore import _cases as cases
from mdcore._case_file import load_case_file, measurements_template, with_measurements
from mdcore._cli import main
from mdcore._export import NROY_ROWS_PER_WAVE, nroy_csv
from mdcore._history_matching import history_match_case

#: What a spreadsheet runs when a cell starts with it.
FORMULA = ("=", "+", "-", "@", "\t", "\r")
#: Names a shared case file could carry: formulas, and commas, quotes and a newline.
HOSTILE = {"x": "@SUM(1,2)", "y": '=HYPERLINK("http://evil/?,x","click")',
           "slope": "=1+2", "intercept": "-2+3,\nnext"}


def hostile_case(folder):
    """A case folder whose input, output and parameter names are spreadsheet formulas."""
    (folder / "toy_sim.py").write_text(SIMULATOR, encoding="utf-8")
    data = CSV.replace("x,y,test", ",".join(csv_quote(HOSTILE[k]) for k in ("x", "y"))
                       + ",test")
    (folder / "data.csv").write_text(data, encoding="utf-8")
    toml = case_toml("toy_sim:linear")
    for key, name in HOSTILE.items():
        old = {"x": 'inputs = ["x"]', "y": 'outputs = ["y"]', "slope": 'name = "slope"',
               "intercept": 'name = "intercept"'}[key]
        new = old.replace(f'"{key}"', json.dumps(name))
        toml = toml.replace(old, new)
    path = folder / "case.toml"
    path.write_text(textwrap.dedent(toml), encoding="utf-8")
    return path


def csv_quote(text: str) -> str:
    return '"' + text.replace('"', '""') + '"'


def is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def test_tables_read_with_plain_pandas_and_no_cell_is_a_formula(tmp_path, capsys):
    path = hostile_case(tmp_path)
    out = tmp_path / "tables"
    assert main(["run", str(path), "--methods", "1", "2", "--n-s", "20", "--n-candidates",
                 "3000", "--csv", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["nroy.csv", "nroy.json",
                                                      "predictions.csv", "predictions.json"]
    for name in ("nroy.csv", "predictions.csv"):
        text = (out / name).read_text(encoding="utf-8")
        rows = list(csv.reader(text.splitlines(keepends=True)))
        assert len({len(r) for r in rows}) == 1                    # one table, no # line
        for cell in (c for r in rows for c in r):
            assert not cell.startswith(FORMULA) or is_number(cell), cell
    nroy = pd.read_csv(out / "nroy.csv")
    assert list(nroy.columns) == ["wave", "'=1+2 [-]", "'-2+3,\nnext [-]", "implausibility"]
    assert all(dtype.kind in "if" for dtype in nroy.dtypes)       # numbers stay numbers
    assert (nroy["'-2+3,\nnext [-]"] < 0).any()                        # negative, not escaped
    pred = pd.read_csv(out / "predictions.csv")
    assert list(pred.columns[:3]) == ["method", "output", "'@SUM(1,2) [-]"]
    assert set(pred["output"]) == {"'" + HOSTILE["y"]} and set(pred["method"]) == {1, 2}
    assert pred["delta_true"].isna().all() and pred["z_sd"].dtype.kind == "f"
    meta = json.loads((out / "nroy.json").read_text(encoding="utf-8"))
    assert meta["threshold"] == 3.0 and meta["rule"] == "max"
    assert [w["rows"] for w in meta["waves"]] == nroy["wave"].value_counts(sort=False).tolist()
    assert json.loads((out / "predictions.json").read_text())["seed"] == 0
    assert "wrote " + str(out / "nroy.json") in capsys.readouterr().out


def test_the_measurements_template_is_plain_csv_and_reads_back(tmp_path):
    for name in cases.names():
        c = cases.load(name)
        table = pd.read_csv(io.StringIO(measurements_template(c)))
        assert list(table.columns) == [*c.x_names, *c.output_names, "test"]
        np.testing.assert_array_equal(table[list(c.output_names)].to_numpy()[:len(c.z_train)],
                                      c.z_train)
    case = load_case_file(hostile_case(tmp_path))
    text = measurements_template(case)
    assert text.splitlines()[0] == ('"\'@SUM(1,2)","\'=HYPERLINK(""http://evil/?,x"",'
                                    '""click"")",test')
    back = with_measurements(case, text, source="mine.csv")       # the escape reads back
    np.testing.assert_array_equal(back.z_test, case.z_test)


def test_the_nroy_table_keeps_a_sample_of_each_wave(tmp_path):
    """Every wave's NROY set would be 22 MB for the app's beam-1d teaching run: each wave
    keeps at most NROY_ROWS_PER_WAVE candidates (the first: a uniform sample of the set),
    with 7 significant digits."""
    case = cases.load("beam-1d")
    design = scipy.stats.qmc.scale(scipy.stats.qmc.LatinHypercube(d=2, seed=0).random(4),
                                   *case.theta_bounds.T)              # the teaching preset's
    hm = history_match_case(case, n_candidates=30_000, initial_design=design, n_runs=3,
                            convergence_ratio=0.1, max_waves=3)
    text = nroy_csv(hm, case.theta_names, case.theta_units)
    table = pd.read_csv(io.StringIO(text))
    assert len(hm.waves) >= 2 and max(len(w.nroy) for w in hm.waves) > NROY_ROWS_PER_WAVE
    for w in hm.waves:
        rows = table[table["wave"] == w.index]
        assert len(rows) == min(len(w.nroy), NROY_ROWS_PER_WAVE)
        np.testing.assert_allclose(rows.iloc[:, 1:3].to_numpy(), w.nroy[:len(rows)],
                                   rtol=5e-7)
        assert (rows["implausibility"] <= hm.problem.options.threshold * (1 + 5e-7)).all()
    assert len(text) / len(table) < 40                  # bytes per row: 7 digits, not 17
