"""The fidelity study: seeds, executors, the summary and the paper's patterns."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from mdcore._cli import main
from mdcore._pipeline import Settings
from mdcore._study import PAPER, Study, parse_seeds, study

TINY = Settings(n_s=10, n_phi=3, n_iter=400, burn_in=100)


def test_parse_seeds():
    assert parse_seeds("0-3") == (0, 1, 2, 3)
    assert parse_seeds(" 4, 1-2 ,9") == (4, 1, 2, 9)
    for bad in ("", "3-1", "-1", "a", "1,1", "0-2,2"):
        with pytest.raises(ValueError, match="seeds"):
            parse_seeds(bad)


def test_executor_gives_the_serial_numbers():
    serial = study("beam-2d", "0-1", methods=[1, 3], settings=TINY)
    with ThreadPoolExecutor(max_workers=2) as pool:
        threaded = study("beam-2d", [0, 1], methods=["1", "3"], settings=TINY, executor=pool)
    assert serial.seeds == threaded.seeds == (0, 1)
    for m in ("1", "3"):
        for metric in ("nmse_z", "nmse_delta", "lpl"):
            np.testing.assert_array_equal(serial.values(m, metric), threaded.values(m, metric))
    # The summary is the mean and the sample sd over seeds of each run's numbers.
    v = np.array([r["methods"]["3"]["metrics"]["nmse_delta"] for r in serial.runs])
    s = serial.summary()["3"]["nmse_delta"]
    np.testing.assert_allclose(s["mean"], v.mean(axis=0))
    np.testing.assert_allclose(s["sd"], v.std(axis=0, ddof=1))
    assert "ess" in serial.summary()["3"] and "ess" not in serial.summary()["1"]
    d = serial.to_dict()
    assert d["paper"] == PAPER["beam-2d"] and len(d["runs"]) == 2


def fake_run(delta, cov2, width=(0.1, 0.2, 0.3, 0.3), nmse_z=((1.0, 2.0),) * 4):
    methods = {}
    for m, d, c, wd, nz in zip(("1", "2", "3", "koh"), delta, cov2, width, nmse_z):
        metrics = {k: [0.5, 0.5] for k in ("mmd", "lpl", "coverage_z_2sd", "coverage_z_3sd",
                                           "coverage_delta_3sd", "rmse_delta", "sd_z")}
        metrics.update(nmse_delta=[d, d], coverage_delta_2sd=[c, c], sd_delta=[wd, wd],
                       nmse_z=list(nz))
        methods[m] = {"metrics": metrics, "importance": None}
    return {"methods": methods}


def test_patterns_by_hand():
    runs = (fake_run([2.0, 3.0, 1.0, 40.0], [0.7, 0.9, 1.0, 1.0]),
            fake_run([2.0, 3.0, 3.0, 20.0], [0.7, 1.0, 1.0, 1.0]))
    p = Study("beam-1d", (0, 1), TINY, runs).patterns()
    assert p["koh_delta_ratio"] == pytest.approx(30.0 / 2.0) and p["koh_10x_worse"]
    assert p["s3_rank"] == 1                          # mean 2.0 ties scenario 1's 2.0: rank 1
    assert p["coverage_rises"] and p["coverage_delta_2sd"] == pytest.approx([0.7, 0.95, 1.0])
    assert p["band_widens"] and p["sd_delta"] == pytest.approx([0.1, 0.2, 0.3])
    assert p["hardest_output"] == {"1": 2, "2": 2, "3": 2}
    worse = (fake_run([1.0, 3.0, 4.0, 5.0], [0.9, 0.8, 1.0, 1.0], width=(0.3, 0.2, 0.4, 0.1),
                      nmse_z=((3.0, 1.0), (2.0, 2.5), (1.0, 1.0), (9.0, 9.0))),)
    q = Study("beam-1d", (0,), TINY, worse).patterns()
    assert q["koh_delta_ratio"] == pytest.approx(5.0) and not q["koh_10x_worse"]
    assert q["s3_rank"] == 3 and not q["coverage_rises"] and not q["band_widens"]
    assert q["hardest_output"] == {"1": 1, "2": 2, "3": 1} and q["best_average_nmse_z"] == "3"


def test_bad_input_and_cli(tmp_path, capsys):
    with pytest.raises(ValueError, match="'beam-9' is not a valid case name"):
        study("beam-9", [0])
    with pytest.raises(ValueError, match="seeds is empty"):
        study("beam-2d", [])
    with pytest.raises(ValueError, match="non-negative integers"):
        study("beam-2d", [0, -1])
    path = tmp_path / "study.json"
    assert main(["study", "beam-2d", "--seeds", "0-1", "--scenarios", "1", "2", "--n-s", "8",
                 "--workers", "1", "--json", str(path)]) == 0
    out = capsys.readouterr().out
    assert "mean ± sd over seeds" in out and "[0.433]" in out and path.exists()
    assert main(["study", "beam-2d", "--seeds", "2-1"]) == 2
    assert "seeds must look like" in capsys.readouterr().err


def test_workers_in_processes_finish_with_the_serial_numbers(tmp_path):
    """``study --workers 2`` from a fresh command line (whose background kernel warm-up
    thread a forked worker would inherit mid-lock and hang on) gives the serial run's
    numbers."""
    import json
    import subprocess
    import sys

    def run(workers: str) -> dict:
        path = tmp_path / f"study-{workers}.json"
        subprocess.run([sys.executable, "-m", "mdcore", "study", "beam-1d", "--seeds", "0-1",
                        "--methods", "1", "--n-s", "20", "--n-phi", "10", "--workers", workers,
                        "--json", str(path)], check=True, timeout=240, capture_output=True)
        data = json.loads(path.read_text())
        for run_ in data["runs"]:
            for entry in run_["methods"].values():
                entry.pop("seconds", None)
        return data["runs"]

    assert run("2") == run("1")
