"""Exports and the command line for a researcher (issue 41): plain CSVs whose headings say
each unit once, files only where asked (folders made), exit 2 when everything is ruled out
or a case file has a typo, advice without "output 1" on a one-output case."""

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest

import mdcore
from mdcore._cli import main
from mdcore._export import with_unit
from mdcore._pipeline import ImportanceDiagnostics, _advice

LAB = Path(__file__).resolve().parent.parent / "examples" / "beam_lab" / "beam_lab.toml"
FAST = ["--methods", "1", "--n-candidates", "2000"]


def test_every_public_name_imports():
    namespace: dict = {}
    exec("from mdcore import *", namespace)            # every name in __all__ must exist
    assert set(mdcore.__all__) <= set(namespace)
    assert namespace["HistoryMatchOptions"]().threshold == 3.0


def test_headings_say_each_unit_once(tmp_path):
    assert main(["run", str(LAB), *FAST, "--csv", str(tmp_path)]) == 0
    pred = pd.read_csv(tmp_path / "predictions.csv")          # plain pandas, no comment=
    assert list(pred.columns[:3]) == ["method", "output", "position_m"]
    assert pred["position_m"].between(0.0, 2.0).all() and len(pred) == pred["method"].size
    nroy = pd.read_csv(tmp_path / "nroy.csv")
    assert list(nroy.columns) == ["wave", "E [GPa]", "w0 [mm]", "implausibility"]
    assert nroy["E [GPa]"].between(150.0, 250.0).all()
    for name in ("nroy.csv", "predictions.csv"):
        assert not (tmp_path / name).read_text(encoding="utf-8").startswith("#")
        assert json.loads((tmp_path / name.replace(".csv", ".json")).read_text())["case"] \
            == "beam-lab"
    assert [with_unit("mass (kg)", "kg"), with_unit("f1 Hz", "Hz"), with_unit("nu", "-"),
            with_unit("E", "")] == ["mass (kg)", "f1 Hz", "nu [-]", "E"]


def test_run_writes_nothing_unless_asked(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(LAB), *FAST]) == 0
    assert list(tmp_path.iterdir()) == []


def test_asked_for_files_go_into_a_new_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(LAB), *FAST, "--json", "results/run.json",
                 "--csv", "results"]) == 0
    assert sorted(p.name for p in (tmp_path / "results").iterdir()) == [
        "nroy.csv", "nroy.json", "predictions.csv", "predictions.json", "run.json"]
    assert json.loads((tmp_path / "results" / "run.json").read_text())["case"] == "beam-lab"


def test_a_run_that_rules_out_everything_exits_2(capsys):
    assert main(["run", str(LAB), *FAST, "--threshold", "0.01"]) == 2
    assert "nothing is non-implausible" in capsys.readouterr().err


def test_a_case_file_typo_is_an_unknown_key(tmp_path, capsys):
    for name in ("beam_lab_simulator.py", "measurements.csv"):
        shutil.copy(LAB.parent / name, tmp_path)
    text = LAB.read_text(encoding="utf-8").replace("noise_var =", "noise_vr =")
    (tmp_path / "lab.toml").write_text(text, encoding="utf-8")
    assert main(["run", str(tmp_path / "lab.toml"), *FAST]) == 2
    err = capsys.readouterr().err
    assert "unknown key(s) 'noise_vr' (did you mean 'noise_var'?)" in err


@pytest.mark.parametrize("n_out", [1, 5])
def test_advice_names_the_output_only_when_there_are_several(n_out):
    low = ImportanceDiagnostics(ess=(2.0,) * n_out, ess_phi=(1.1,) * n_out,
                                skipped_mass=(0.0,) * n_out, k_hat=(1.3,) * n_out,
                                n_pairs=100, n_phi=10, proposal="prior")
    advice = _advice(low, None)
    assert len(advice) == n_out and all("k̂ 1.30" in a for a in advice)
    assert [("output" in a) for a in advice] == [n_out > 1] * n_out
    if n_out > 1:
        assert advice[-1].startswith("scenario 3, output 5:")
