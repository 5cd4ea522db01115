"""The command line: the reproduce table and JSON, method choice, bad input."""

import json

import numpy as np
import pytest

from mdcore._cli import main


def test_reproduce_writes_the_documented_json(tmp_path, capsys):
    path = tmp_path / "out.json"
    assert main(["reproduce", "beam-1d", "--n-s", "40", "--n-phi", "10", "--n-iter", "3000",
                 "--burn-in", "1000", "--json", str(path)]) == 0
    out = json.loads(path.read_text())
    assert out["case"] == "beam-1d" and out["seed"] == 0 and out["schema_version"] == 5
    assert out["settings"]["n_s"] == 40 and out["settings"]["n_phi"] == 10
    hm = out["history_matching"]
    assert hm["truth_nroy"] is True and hm["status"] == "converged"
    assert len(hm["nroy_fraction"]) == hm["waves"] and len(hm["theta_map"]) == 2
    assert list(out["methods"]) == ["1", "2", "3", "koh"]      # KOH by default on beam-1d
    for label, e in out["methods"].items():
        for key in ("nmse_z", "nmse_delta", "mmd", "lpl", "coverage_z_3sd",
                    "coverage_delta_3sd"):
            assert len(e["metrics"][key]) == 1 and np.isfinite(e["metrics"][key][0])
        assert (e["importance"] is None) == (label != "3") and e["seconds"] > 0
        assert (e["chain"] is None) == (label != "koh")
    (check,) = hm["validation"]                 # one wave: its leave-one-run-out summary
    assert check["wave"] == 1 and check["runs"] == 25 and check["wrongly_ruled_out"] == 0
    assert 0 <= check["share_beyond_3"] < 0.05 and not check["too_confident"]
    assert len(hm["space_removed"]) == 1 and len(hm["space_removed"][0]) == 2
    for label in ("1", "2", "3"):               # the θ–δ share of each decoupled scenario
        td = out["methods"][label]["theta_delta"]
        assert len(td["share"]) == 1 and 0 <= td["share"][0] <= 1
        assert td["mostly_theta"] == [td["share"][0] > 0.5]
    assert out["methods"]["1"]["theta_delta"]["share"] == [0.0]
    assert out["methods"]["koh"]["theta_delta"] is None
    chain = out["methods"]["koh"]["chain"]
    assert chain["n_iter"] == 3000 and chain["burn_in"] == 1000
    assert 0 < chain["acceptance_rate"] < 1 and len(chain["ess"]) == 2
    table = capsys.readouterr().out
    assert "NMSE z %" in table and "tip deflection" in table and "KOH chain" in table
    lines = table.splitlines()
    start = next(i for i, line in enumerate(lines) if "NMSE z %" in line)
    header, rows = lines[start], lines[start + 1:lines.index("", start)]
    assert len(rows) == 4 and all(len(r) == len(header) for r in rows)   # aligned columns
    s1 = next(r for r in rows if r.split()[0] == "1")
    assert s1.split()[-3:-1] == ["—", "—"]         # no ESS for scenario 1: a dash, never NaN
    assert "nan" not in table.lower()
    assert "emulator check, leaving out each run" in table and "wrongly ruled out" in table
    assert "share from θ" in table and "space removed along each parameter's range" in table
    if out["methods"]["2"]["theta_delta"]["mostly_theta"][0]:
        assert "Scenario 2, tip deflection: " in table and "not physics" in table


def test_method_choice_and_bad_labels(capsys):
    assert main(["reproduce", "beam-2d", "--scenarios", "1", "koh", "--n-s", "10",
                 "--n-phi", "1", "--n-iter", "600", "--burn-in", "100"]) == 0
    table = capsys.readouterr().out
    assert "KOH chain: 600 iterations" in table
    with pytest.raises(SystemExit):
        main(["reproduce", "beam-1d", "--scenarios", "4"])
    assert main(["reproduce", "beam-1d", "--n-s", "0"]) == 2
    assert "n_s must be an integer ≥ 1" in capsys.readouterr().err
    assert main(["reproduce", "beam-1d", "--n-iter", "100", "--burn-in", "100"]) == 2
    assert "burn_in must be smaller than n_iter" in capsys.readouterr().err


def test_history_match_and_cases(capsys):
    assert main(["cases"]) == 0
    listing = capsys.readouterr().out
    assert all(name in listing for name in ("beam-1d", "beam-2d", "shear-5"))
    assert main(["history-match", "beam-1d", "--n-candidates", "5000"]) == 0
    out = capsys.readouterr().out
    assert "θ_MAP: l_cr = " in out and "NROY %" in out
    assert main(["history-match", "beam-1d", "--v-m", "1e-6", "--n-candidates", "2000",
                 "--threshold", "0.5"]) == 2               # everything ruled out: bad input
    assert "Raise V_m" in capsys.readouterr().out
    assert main(["history-match", "beam-1d", "--threshold", "0"]) == 2
    assert "threshold T must be a positive number" in capsys.readouterr().err


def test_run_own_case_file_writes_tables_and_json(tmp_path, capsys):
    from pathlib import Path
    example = Path(__file__).resolve().parent.parent / "examples" / "beam_lab" / "beam_lab.toml"
    out = tmp_path / "out"
    assert main(["run", str(example), "--n-s", "20", "--n-phi", "10", "--scenarios", "1", "3",
                 "--csv", str(out), "--json", str(tmp_path / "run.json")]) == 0
    table = capsys.readouterr().out
    assert "beam-lab" not in table or "deflection_mm" in table
    assert (out / "nroy.csv").exists() and (out / "predictions.csv").exists()
    d = json.loads((tmp_path / "run.json").read_text())
    assert d["case"] == "beam-lab" and list(d["methods"]) == ["1", "3"]
    assert d["methods"]["1"]["metrics"]["nmse_delta"] is None      # δ unknown: null, not NaN
    # Exit codes: 2 for bad input (a malformed file), 1 for a failure (an unwritable path).
    assert main(["run", str(tmp_path / "missing.toml")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["run", str(example), "--n-s", "5", "--n-phi", "2", "--scenarios", "1",
                 "--json", str(tmp_path / "run.json" / "dir.json")]) == 1   # under a file
    assert "FileExistsError" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["cases", "history-match", "reproduce", "run", "study"])
def test_every_subcommand_has_examples_and_exit_codes_in_help(command, capsys):
    with pytest.raises(SystemExit) as done:
        main([command, "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    assert "example" in text and f"python -m mdcore {command}" in text
    assert "exit codes: 0 done; 2 bad input" in text


def test_history_options_reach_the_history_match(capsys):
    assert main(["history-match", "beam-1d", "--n-candidates", "3000", "--n-runs", "6",
                 "--convergence-ratio", "0.05", "--max-waves", "3", "--v-m", "0.04"]) == 0
    out = capsys.readouterr().out
    header = next(line for line in out.splitlines() if "NROY %" in line)
    rows = [line for line in out.splitlines()
            if line.split() and line.split()[0].isdigit() and len(line) == len(header)]
    runs = [int(r.split()[2]) for r in rows]
    assert len(rows) >= 2 and runs == [25] + [6] * (len(rows) - 1)   # design, then --n-runs
    assert main(["history-match", "shear-5", "--v-m", "0.1", "0.2"]) == 2
    assert "--v-m takes 1 value or one per output (5 for shear-5" in capsys.readouterr().err


def test_multivariate_rule_options(capsys):
    assert main(["history-match", "beam-2d", "--rule", "multivariate", "--v-m-length", "0.2",
                 "--n-candidates", "3000", "--max-waves", "1"]) == 0
    assert "θ_MAP: E = " in capsys.readouterr().out
    assert main(["history-match", "shear-5", "--rule", "multivariate", "--v-m-corr", "0.5",
                 "--chi2-probability", "0.99", "--n-candidates", "3000", "--max-waves", "1"]) == 0
    capsys.readouterr()
    assert main(["history-match", "shear-5", "--rule", "multivariate", "--v-m-corr", "-0.3",
                 "--n-candidates", "3000"]) == 2
    assert "V_m_corr is not positive definite: its smallest eigenvalue is -0.2" \
        in capsys.readouterr().err
    assert main(["history-match", "shear-5", "--v-m-corr", "0.1", "0.2"]) == 2
    assert "--v-m-corr takes 1 value (ρ for every pair of outputs) or the 5 × 5 = 25" \
        in capsys.readouterr().err
    assert main(["history-match", "beam-1d", "--v-m-length", "-1"]) == 2
    assert "V_m_length must be one length ≥ 0" in capsys.readouterr().err


def test_warnings_are_summarised_once_in_words(capsys, monkeypatch):
    import warnings as w

    from mdcore import _cli as cli
    from mdcore._exceptions import ConvergenceWarning

    def noisy(args):
        for _ in range(3):
            w.warn("the optimiser stopped early", ConvergenceWarning, stacklevel=1)
        w.warn("something else", RuntimeWarning, stacklevel=1)
        return 0

    monkeypatch.setattr(cli, "_cmd_cases", noisy)
    assert main(["cases"]) == 0
    err = capsys.readouterr().err
    assert "4 warning(s) while running, each listed once" in err
    assert "did not converge (×3): the optimiser stopped early" in err
    assert err.count("the optimiser stopped early") == 1


def test_progress_bars_only_on_a_terminal(capsys, monkeypatch):
    import io

    from mdcore import _cli as cli

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    with cli._Bar("Scenario 3", 200, "pairs") as bar:      # not a terminal: silent
        bar.fraction(0.5, "pairs")
    assert capsys.readouterr().err == ""
    fake = Terminal()
    monkeypatch.setattr(cli.sys, "stderr", fake)
    with cli._Bar("Scenario 3", 200, "pairs") as bar:
        bar._bar.ncols, bar._bar.nrows = 100, 40
        bar.fraction(0.5, "scoring pairs")
    shown = fake.getvalue()
    assert "Scenario 3:  50%" in shown and "100/200" in shown and "scoring pairs" in shown


def test_local_dask_cluster_gives_the_serial_numbers(tmp_path):
    pytest.importorskip("distributed")
    serial, cluster = tmp_path / "serial.json", tmp_path / "cluster.json"
    base = ["reproduce", "beam-1d", "--n-s", "20", "--n-phi", "5", "--methods", "1",
            "--n-candidates", "3000"]
    assert main(base + ["--json", str(serial)]) == 0
    assert main(base + ["--workers", "2", "--json", str(cluster)]) == 0
    a, b = json.loads(serial.read_text()), json.loads(cluster.read_text())
    assert a["history_matching"] == b["history_matching"]
    assert a["methods"]["1"]["metrics"] == b["methods"]["1"]["metrics"]


def test_a_too_confident_emulator_is_reported_once_with_its_advice(capsys, monkeypatch):
    """history-match prints each wave's LOO check; a wave whose emulator is too confident
    gets its advice beside the table, not again in the warnings summary."""
    from test_diagnostics import with_params

    from mdcore import _history_matching as history_matching

    fit = history_matching.fit_emulator

    def too_confident(*args, **kwargs):
        em = fit(*args, **kwargs)
        return with_params(em, em.log_params + np.r_[-np.log(1e3), [np.log(1 / 30)] * 3,
                                                     -np.log(1e3)])

    monkeypatch.setattr(history_matching, "fit_emulator", too_confident)
    assert main(["history-match", "beam-1d", "--n-candidates", "5000"]) == 0
    out, err = capsys.readouterr()
    assert "emulator check, leaving out each run" in out
    assert "! wave 1: " in out and "too confident" in out and "Add simulator runs" in out
    assert "wave 1: " not in err
