"""Own simulators on a real Dask cluster: a ``dask scheduler`` and ``dask worker``
processes started here, and ``python -m mdcore run CASE.toml --dask tcp://…`` against them
(issue 40, item 10).

The case's simulator module lives in ``tmp_path``, outside every installed package, and
the workers run in another folder with nothing of it on their path: the run only works
if the module travels to them (by value, :class:`mdcore._runs.SimulatorProcess`).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import time

import pytest
from test_own_simulators import CSV, case_toml

from mdcore._cli import main

#: The simulator: a helper module beside it too, which must travel as well.
SIMULATOR = '''
import numpy as np
from shape_helper import as_outputs


def linear(X, theta):
    theta = np.atleast_2d(theta)
    return as_outputs(theta[:, :1] * X[None, :, 0] + theta[:, 1:2])
'''
HELPER = '''
def as_outputs(y):
    return y[..., None]
'''


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def cluster(tmp_path):
    """The address of a scheduler with two single-threaded worker processes; torn down
    at the end."""
    pytest.importorskip("distributed")
    port, elsewhere = _free_port(), tmp_path / "workers"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    address = f"tcp://127.0.0.1:{port}"
    procs = [subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host",
                               "127.0.0.1", "--port", str(port), "--no-dashboard"],
                              cwd=elsewhere, env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)]
    procs.append(subprocess.Popen([sys.executable, "-m", "dask", "worker", address,
                                   "--nworkers", "2", "--nthreads", "1", "--no-dashboard",
                                   "--local-directory", str(elsewhere)],
                                  cwd=elsewhere, env={**env, "MDCORE_NUM_THREADS": "1"},
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    try:
        from distributed import Client
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for proc in reversed(procs):
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def test_own_simulator_on_a_real_cluster_gives_the_serial_numbers(tmp_path, cluster):
    case = tmp_path / "case"
    case.mkdir()
    (case / "toy_sim.py").write_text(SIMULATOR, encoding="utf-8")
    (case / "shape_helper.py").write_text(HELPER, encoding="utf-8")
    (case / "data.csv").write_text(CSV, encoding="utf-8")
    path = case / "case.toml"
    toml = case_toml("toy_sim:linear").replace("initial_design = 10", "initial_design = 4")
    path.write_text(textwrap.dedent(toml), encoding="utf-8")
    base = ["run", str(path), "--methods", "1", "2", "3", "--n-s", "30", "--n-phi", "10",
            "--n-candidates", "3000", "--n-runs", "4", "--convergence-ratio", "1e-4",
            "--max-waves", "3"]
    start = time.monotonic()
    assert main(base + ["--json", str(tmp_path / "serial.json")]) == 0
    assert main(base + ["--dask", cluster, "--json", str(tmp_path / "cluster.json")]) == 0
    serial, remote = (json.loads((tmp_path / f"{n}.json").read_text(encoding="utf-8"))
                      for n in ("serial", "cluster"))
    assert serial["history_matching"]["waves"] >= 2      # runs on the workers in every wave
    assert remote["history_matching"] == serial["history_matching"]
    for m in ("1", "2", "3"):
        assert remote["methods"][m]["metrics"] == serial["methods"][m]["metrics"]
    assert time.monotonic() - start < 120
