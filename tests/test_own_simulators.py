"""Own simulators that hang, exit or fail: stopped at their timeout, recorded, never the end
of the command line or of the app's server (issue 40, items 7 and 11); and no file written
beside them (issue 41, item 10).

Every test goes through the path a user takes: a case folder on disk (TOML, CSV and a
simulator module in ``tmp_path``, outside any package), then ``python -m mdcore`` (its
``main``) or ``panel serve``.
"""

from __future__ import annotations

import html
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from test_case_file import CSV, TOML

from mdcore._cli import main

ROOT = Path(__file__).resolve().parent.parent

SIMULATOR = '''
import os, sys, time
from pathlib import Path
import numpy as np

HERE = Path(__file__).parent


def linear(X, theta):
    theta = np.atleast_2d(theta)
    return (theta[:, :1] * X[None, :, 0] + theta[:, 1:2])[..., None]


def hangs_above(X, theta):
    """Hangs (forever, for a test) where the slope is above 1.8, noting its process id."""
    if np.any(np.atleast_2d(theta)[:, 0] > 1.8):
        (HERE / f"hung-{os.getpid()}.pid").write_text("")
        time.sleep(600)
    return linear(X, theta)


def exits_above(X, theta):
    if np.any(np.atleast_2d(theta)[:, 0] > 1.8):
        sys.exit(3)
    if np.any(np.atleast_2d(theta)[:, 0] < 0.2):
        raise ValueError("<b>stiffness</b> below the gauge's range")
    return linear(X, theta)


def always_exits(X, theta):
    sys.exit(3)
'''

HANGS_AT_IMPORT = '''
import os, time
from pathlib import Path
(Path(__file__).parent / f"hung-{os.getpid()}.pid").write_text("")
time.sleep(600)

def linear(X, theta):
    return X
'''

def case_toml(function: str, simulator: str = "") -> str:
    """test_case_file's case file with another simulator function, more [simulator] keys
    and a 10-run initial design."""
    return (TOML.replace("toy_sim:linear", function)
            .replace('path = "."', 'path = "."\n' + simulator)
            .replace("V_m = [0.01]", "V_m = [0.01]\ninitial_design = 10"))


def case_folder(folder: Path, function: str, simulator: str = "") -> Path:
    """A case folder: the measurements, the simulators and a case file naming one."""
    (folder / "toy_sim.py").write_text(SIMULATOR, encoding="utf-8")
    (folder / "hangs_at_import.py").write_text(HANGS_AT_IMPORT, encoding="utf-8")
    (folder / "data.csv").write_text(CSV, encoding="utf-8")
    path = folder / "case.toml"
    path.write_text(textwrap.dedent(case_toml(function, simulator)), encoding="utf-8")
    return path


def hung_processes(folder: Path) -> list[int]:
    """Process ids the hanging simulators noted that are still running."""
    alive = []
    for note in folder.glob("hung-*.pid"):
        pid = int(note.stem.split("-")[1])
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            continue
        alive.append(pid)
    return alive


def test_runs_past_the_timeout_are_stopped_and_recorded(tmp_path, capsys):
    """[simulator] timeout: the run that hangs is killed after it, counts as failed, and the
    JSON and the report hold its θ and message; the other runs go on."""
    path = case_folder(tmp_path, "toy_sim:hangs_above", "timeout = 1.5")
    out = tmp_path
    start = time.monotonic()
    assert main(["run", str(path), "--methods", "1", "--n-candidates", "2000",
                 "--json", str(out / "run.json"), "--out", str(out / "report.html")]) == 0
    elapsed = time.monotonic() - start
    doc = json.loads((out / "run.json").read_text(encoding="utf-8"))
    assert doc["schema_version"] == 5
    failed = doc["history_matching"]["failed_runs"]
    assert len(failed) == doc["history_matching"]["waves"]
    # The Latin hypercube of 10 runs puts exactly one slope in (1.8, 2]: that run hung.
    assert [len(f) for f in failed[:1]] == [1]
    assert failed[0][0]["message"] == "timed out after 1.5 s"
    assert failed[0][0]["theta"][0] > 1.8 and len(failed[0][0]["theta"]) == 2
    assert len(list(tmp_path.glob("hung-*.pid"))) == sum(map(len, failed))
    assert hung_processes(tmp_path) == []                  # stopped, not abandoned
    assert elapsed < 120
    report = (out / "report.html").read_text(encoding="utf-8")
    assert "Failed simulator runs" in report and "timed out after 1.5 s" in report
    assert "1 of 10 simulator runs failed and were dropped (first: timed out after 1.5 s)" \
        in capsys.readouterr().out


def test_a_simulator_calling_sys_exit_is_a_failed_run_with_a_message(tmp_path, capsys):
    """sys.exit in the simulator ends neither the command line nor the run: the run fails,
    named; an exception's HTML in the report is escaped."""
    path = case_folder(tmp_path, "toy_sim:exits_above")
    out = tmp_path
    assert main(["run", str(path), "--methods", "1", "--n-candidates", "2000",
                 "--json", str(out / "run.json"), "--out", str(out / "report.html")]) == 0
    failed = json.loads((out / "run.json").read_text())["history_matching"]["failed_runs"][0]
    assert sorted(f["message"] for f in failed) == [
        "ValueError: <b>stiffness</b> below the gauge's range",
        "the simulator called sys.exit(3), which ends its process"]
    # The page's Div holds HTML inside the document's JSON, itself HTML-escaped once.
    div = html.unescape((out / "report.html").read_text(encoding="utf-8"))
    assert "&lt;b&gt;stiffness&lt;/b&gt;" in div and "<b>stiffness</b>" not in div

    path = case_folder(tmp_path, "toy_sim:always_exits")
    assert main(["run", str(path), "--methods", "1"]) == 2
    err = capsys.readouterr().err
    assert "toy_sim:always_exits failed at the centre of the parameter box [1.0, 0.0]: the " \
           "simulator called sys.exit(3), which ends its process" in err


def test_timeout_on_the_command_line_bounds_a_simulator_that_hangs_at_import(tmp_path, capsys):
    path = case_folder(tmp_path, "hangs_at_import:linear")
    start = time.monotonic()
    assert main(["run", str(path), "--timeout", "2", "--methods", "1"]) == 2
    assert time.monotonic() - start < 30
    err = capsys.readouterr().err
    assert "[simulator] function hangs_at_import:linear did not answer within the timeout " \
           "of 2 s at the centre of the parameter box [1.0, 0.0] (its import included); " \
           "raise [simulator] timeout (or --timeout)" in err
    assert len(list(tmp_path.glob("hung-*.pid"))) == 1 and hung_processes(tmp_path) == []


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("warm", [True, False], ids=["at start-up", "at the first visit"])
def test_the_app_server_survives_a_case_whose_simulator_hangs(tmp_path, warm):
    """``panel serve app/main.py --args --case`` with a simulator that hangs at import:
    pages are served once its timeout has passed (at start-up with --warm), the hung
    process is stopped, and SIGTERM stops the server."""
    path = case_folder(tmp_path, "hangs_at_import:linear", "timeout = 2")
    port = _free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "panel", "serve", str(ROOT / "app" / "main.py"), "--address",
         "127.0.0.1", "--port", str(port), *(["--warm"] if warm else []),
         "--args", "--case", str(path)],
        cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline, page = time.monotonic() + 90, None
        while page is None and time.monotonic() < deadline and server.poll() is None:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/main", timeout=30) as r:
                    page = r.read().decode()
            except OSError:
                time.sleep(0.5)
        assert page is not None and "Model Discrepancy Explorer" in page
        assert hung_processes(tmp_path) == [] and list(tmp_path.glob("hung-*.pid"))
        server.send_signal(signal.SIGTERM)
        assert server.wait(timeout=20) is not None
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()
        server.stderr.close()


def test_run_writes_only_what_it_was_asked_for(tmp_path):
    """``python -m mdcore run`` of the worked example (copied) from another folder: the
    files asked for appear, and nothing else in the case's folder or the working folder
    (no __pycache__ beside the simulator: issue 41 item 10)."""
    case, work = tmp_path / "beam_lab", tmp_path / "work"
    work.mkdir()
    shutil.copytree(ROOT / "examples" / "beam_lab", case)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    subprocess.run([sys.executable, "-m", "mdcore", "run", str(case / "beam_lab.toml"),
                    "--methods", "1", "--n-candidates", "2000", "--json", "run.json"],
                   cwd=work, env=env, check=True, capture_output=True, timeout=300)
    after = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    assert [p for p in after if p not in before] == [Path("work/run.json")]


def test_close_from_another_thread_ends_a_running_call(tmp_path):
    """How a caller (the app's Cancel) stops a run that would hang: close() kills the
    process, the waiting call raises at once, and the next call starts a new process."""
    import threading

    from mdcore._runs import SimulatorError, SimulatorProcess
    case_folder(tmp_path, "toy_sim:linear")
    sim = SimulatorProcess("toy_sim", "hangs_above", tmp_path)
    X = np.linspace(0.0, 1.0, 3)[:, None]
    np.testing.assert_array_equal(sim(X, [[1.0, 0.5]])[0, :, 0], X[:, 0] + 0.5)
    cancel = threading.Timer(1.0, sim.close)
    cancel.start()
    start = time.monotonic()
    with pytest.raises(SimulatorError, match=r"the simulator's process ended \(exit code "):
        sim(X, [[1.9, 0.0]], timeout=60)
    assert time.monotonic() - start < 10
    cancel.join()                                   # close() has reaped the process
    assert hung_processes(tmp_path) == []
    np.testing.assert_array_equal(sim(X, [[1.0, 0.0]], timeout=60)[0, :, 0], X[:, 0])
    sim.close()
