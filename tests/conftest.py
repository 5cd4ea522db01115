import importlib.util
import os
from typing import NamedTuple

import numpy as np
import pytest

#: Modules of the ``test`` extra that some tests reach through ``pytest.importorskip``
#: (module -> what needs it). Locally a missing one skips those tests; with
#: ``MDCORE_REQUIRE_EXTRAS=1`` (set by ``.ci/run``) it stops the run before any test.
OPTIONAL_TEST_MODULES = {
    "sklearn": "tests/test_gp.py (scikit-learn reference)",
    "arviz": "tests/test_importance.py (PSIS reference)",
    "numba": "tests/test_compiled.py",
    "distributed": "tests/test_runs.py (Dask executor)",
    "PIL": "tests/test_report.py (screenshot check)",
    "hypothesis": "tests/test_kernels.py (property tests)",
    "playwright": "the browser tests",
}


def pytest_sessionstart(session):
    if os.environ.get("MDCORE_REQUIRE_EXTRAS") != "1":
        return
    missing = {name: why for name, why in OPTIONAL_TEST_MODULES.items()
               if importlib.util.find_spec(name) is None}
    if missing:
        listed = "; ".join(f"{name} (for {why})" for name, why in missing.items())
        raise pytest.UsageError(
            f"MDCORE_REQUIRE_EXTRAS=1 but these test dependencies are not importable: {listed}. "
            "Install them with: pip install -e \".[test]\"")


def missing(reason: str) -> None:
    """Skip a test whose requirement is missing here (a start method, a NumPy internal), or
    fail it under ``MDCORE_REQUIRE_EXTRAS=1`` (CI), where every test must run."""
    if os.environ.get("MDCORE_REQUIRE_EXTRAS") == "1":
        pytest.fail(f"MDCORE_REQUIRE_EXTRAS=1 but {reason}")
    pytest.skip(reason)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


class Served(NamedTuple):
    """``panel serve app/main.py`` of a module's browser tests (see :func:`server`)."""

    proc: object             # the subprocess.Popen
    url: str
    log: object              # browser.ServerLog: the server's output


@pytest.fixture(scope="module")
def server():
    """The app served on a free port for one test module's browser tests (skipped, or
    failed under ``MDCORE_REQUIRE_BROWSER=1``, without Chromium and Playwright)."""
    from browser import require_browser, serve_app
    require_browser()
    proc, url, log = serve_app()
    yield Served(proc, url, log)
    proc.terminate()
    proc.wait(timeout=10)


@pytest.fixture(scope="module")
def browser():
    """Debian's headless Chromium for one test module, closed afterwards."""
    from browser import chromium, require_browser
    require_browser()
    yield from chromium()
