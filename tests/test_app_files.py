"""Your data in, results out, in the app: uploaded measurements, saved and reopened
sessions, downloads, and results kept per case."""

import json
import warnings

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("panel")
import holoviews as hv  # noqa: E402
import panel as pn  # noqa: E402
from bokeh.document import Document  # noqa: E402

from mdcore import _cases as cases  # noqa: E402
from mdcore._case_file import measurements_template, with_measurements  # noqa: E402
from mdcore._pipeline import Method  # noqa: E402
from mdcore_app import session  # noqa: E402
from mdcore_app.state import ExplorerState  # noqa: E402
from mdcore_app.views import ExplorerView  # noqa: E402

hv.extension("bokeh")
SMALL = {"preset": "paper", "n_candidates": 4000, "n_s": 30, "n_phi": 8}
S123 = [Method.S1, Method.S2, Method.S3]


def small_state(case="beam-1d", **extra):
    s = ExplorerState()
    s.case_name = case
    s.param.update(**{**SMALL, **extra})
    return s


def errors_of(s):
    """Collect every notification of ``s`` (one per event)."""
    seen = []
    s.param.watch(lambda e: seen.append(s.error), "n_errors")
    return seen


def quiet(fn, *args):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args)


def lab_csv(case_name="beam-1d", shift=0.02):
    """Measurements in the template layout: the case's data with every reading shifted."""
    c = cases.load(case_name)
    lines = measurements_template(c).splitlines()
    out = lines[:1]                            # the header
    n_out = c.n_out
    for row in lines[1:]:
        cells = row.split(",")
        for j in range(c.d_x, c.d_x + n_out):
            cells[j] = repr(float(cells[j]) + shift)
        out.append(",".join(cells))
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------------------
# Uploaded measurements


def test_template_round_trips_every_case():
    for name in cases.names():
        c = cases.load(name)
        own = with_measurements(c, measurements_template(c), source="mine.csv")
        np.testing.assert_array_equal(own.X_train, c.X_train)
        np.testing.assert_array_equal(own.z_test, c.z_test)
        assert own.theta_true is None and own.true_delta(c.X_test) is None
        np.testing.assert_array_equal(own.theta_bounds, c.theta_bounds)


def test_uploaded_measurements_become_a_case_of_this_session_only():
    s = small_state()
    other = ExplorerState()
    text = lab_csv()
    assert s.upload_measurements(text.encode(), "my_beam.csv")
    assert s.case_name == "beam-1d · my_beam.csv" and s.error == ""
    np.testing.assert_allclose(s.case.z_train, cases.load("beam-1d").z_train + 0.02,
                               rtol=0, atol=1e-12)
    assert s.case.simulate(s.case.X_train, [[0.5, 200.0]]).shape == (1, 13, 1)
    assert "beam-1d · my_beam.csv" not in other.param.case_name.objects     # per session
    quiet(s.run_discrepancy)                    # history matching first, then the methods
    assert s.error == "" and list(s.results) == S123
    m = s.results[Method.S1].metrics
    assert m.nmse_delta is None and np.isfinite(m.nmse_z[0])       # no true δ for own data
    s.case_name = "beam-2d"
    assert s.base_case_name() == "beam-2d"
    s.case_name = "beam-1d · my_beam.csv"        # the upload stays, with its results
    assert list(s.results) == S123


@pytest.mark.parametrize("data, problem", [
    (b"", "empty"),
    (b"x" * (session.MAX_UPLOAD_BYTES + 1), "more than the 5 MB limit (5,000,000 bytes)"),
    ("crack location,tip deflection,test\n0.2,\xe9,0\n".encode("latin-1"), "not UTF-8"),
    (b"position,deflection\n0.2,0.5\n", "not found in a header with none of them"),
    (b"crack location,tip deflection,test\n", "no data rows"),
    (b"crack location,tip deflection,test\n0.2,0.5,0\n0.3,0.6,2\n", "must be 0"),
    (b"crack location,tip deflection,test\n0.2,0.5,1\n0.3,0.6,1\n", "marks 0 training row(s) (0) and 2 test row(s) (1); at least 3 training"),
    (b"crack location,tip deflection,test\n200,0.5,0\n0.3,0.6,1\n", "far outside"),
    (b"crack location,tip deflection,test\n0.2,0.5,0\n0.3,0.6,1\n", "at least 3"),
    (b"crack location,tip deflection,test\n0.2,__import__('os'),0\n0.3,0.6,1\n",
     "is not a number"),
    (("crack location,tip deflection,test\n" + "0.3,1.0,1\n" * 1001).encode(),
     "more than 1,000 data rows"),
    (("crack location,tip deflection,test\n" + "0.3,1.0,0\n" * 301 + "0.3,1.0,1\n").encode(),
     "301 training rows; at most 300"),
], ids=["empty", "too-big", "latin-1", "wrong-columns", "no-rows", "bad-test-flag",
        "no-training-rows", "wrong-units", "too-few-rows", "code-is-not-run", "too-many-rows",
        "too-many-training-rows"])
def test_a_bad_upload_is_a_notification_and_the_session_keeps_its_case(data, problem):
    s = small_state()
    s.run_to_convergence()
    waves, objects = s.waves, list(s.param.case_name.objects)
    seen = errors_of(s)
    assert not s.upload_measurements(data, "lab.csv")
    assert len(seen) == 1 and problem in seen[0] and "lab.csv" in seen[0]
    assert s.case_name == "beam-1d" and s.waves is waves
    assert list(s.param.case_name.objects) == objects


def test_each_problem_of_an_upload_is_its_own_notification():
    s = small_state()
    seen = errors_of(s)
    bad = b"crack location,tip deflection,test\n0.2,abc,0\n0.3,nan,1\n0.4,0.5\n0.5,0.1,0\n"
    assert not s.upload_measurements(bad, "lab.csv")
    assert len(seen) == 3
    assert "line 2" in seen[0] and "'abc' is not a number" in seen[0]
    assert "line 3" in seen[1] and "not finite" in seen[1]
    assert "line 4" in seen[2] and "2 field(s)" in seen[2]


# ---------------------------------------------------------------------------------------
# Sessions: save, then open, gives the same numbers


def run_small(s, methods=S123):
    s.scenarios = methods
    quiet(s.run_discrepancy)
    assert s.error == "" and list(s.results) == methods
    return s


def test_saved_session_reopens_with_the_same_numbers():
    s = run_small(small_state(n_s=40, seed=3, v_m=0.06, threshold=2.5))
    doc = json.loads(s.session_json())
    assert doc["schema"] == "mdcore-session" and doc["schema_version"] == 1
    assert doc["controls"]["seed"] == 3 and doc["controls"]["scenarios"] == ["1", "2", "3"]
    assert doc["n_waves"] == len(s.waves)
    assert set(doc["run"]["methods"]) == {"1", "2", "3"}
    fresh = ExplorerState()
    statuses = []
    fresh.param.watch(lambda e: statuses.append(e.new), "status")
    assert quiet(fresh.open_session, s.session_json().encode(), "saved.json")
    assert fresh.error == ""
    assert (fresh.v_m, fresh.threshold, fresh.n_s, fresh.seed) == (0.06, 2.5, 40, 3)
    assert len(fresh.waves) == len(s.waves) and list(fresh.results) == S123
    for m in S123:
        assert fresh.results[m].metrics.as_dict() == s.results[m].metrics.as_dict()
        np.testing.assert_array_equal(fresh.results[m].on_extra.delta_var,
                                      s.results[m].on_extra.delta_var)
    assert "every metric equals the saved one" in statuses[-1]


def test_a_session_on_uploaded_data_carries_the_data():
    s = small_state()
    s.upload_measurements(lab_csv(shift=0.03).encode(), "lab.csv")
    run_small(s, [Method.S1])
    fresh = ExplorerState()
    assert quiet(fresh.open_session, s.session_json().encode(), "lab_session.json")
    assert fresh.case_name == "beam-1d · lab.csv" and fresh.error == ""
    np.testing.assert_array_equal(fresh.case.z_train, s.case.z_train)
    assert fresh.results[Method.S1].metrics.as_dict() == s.results[Method.S1].metrics.as_dict()


def test_a_changed_metric_is_reported_on_open():
    s = run_small(small_state(), [Method.S1])
    doc = json.loads(s.session_json())
    doc["run"]["methods"]["1"]["metrics"]["nmse_z"][0] *= 1.5
    fresh = ExplorerState()
    quiet(fresh.open_session, json.dumps(doc).encode(), "edited.json")
    assert "1 metric(s) differ" in fresh.status and "nmse_z" in fresh.status


def good_doc():
    return json.loads(small_state().session_json())


def edit(path, value):
    doc = good_doc()
    *keys, last = path
    target = doc
    for k in keys:
        target = target[k]
    if value is KeyError:
        del target[last]
    else:
        target[last] = value
    return json.dumps(doc).encode()


@pytest.mark.parametrize("data, problem", [
    (b"{not json", "not valid JSON"),
    (b"[1, 2]", "not an mdcore session"),
    (json.dumps({"schema": "other"}).encode(), "not an mdcore session"),
    (edit(["schema_version"], 99), "schema_version 99 is not supported"),
    (edit(["controls", "v_m"], KeyError), "controls.v_m is missing"),
    (edit(["controls", "n_s"], "many"), "controls.n_s must be int"),
    (edit(["controls", "seed"], True), "controls.seed must be int"),
    (edit(["n_waves"], -1), "n_waves"),
    (edit(["case", "name"], "bridge-9"), "'bridge-9' is not in this app"),
    (edit(["controls", "v_m"], -0.5), "V_m"),
    (edit(["controls", "n_phi"], 0), "N_φ"),
    (edit(["controls", "rule"], "mean"), "rule"),
    (edit(["controls", "busy"], True), "controls.busy is not a control of this app"),
    (edit(["controls", "_cache"], {}), "controls._cache is not a control of this app"),
    (edit(["controls", "v_m_length"], -1.0), "ℓ_m"),
    (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
    (b'{"schema": ' + b"9" * 5000 + b"}", "more digits than Python reads"),
], ids=["not-json", "a-list", "other-schema", "newer-version", "missing-control",
        "wrong-type", "bool-for-int", "negative-waves", "unknown-case", "negative-v_m",
        "zero-n_phi", "unknown-rule", "a-result-field", "a-private-attribute",
        "negative-l_m", "deeply-nested", "huge-integer"])
def test_a_bad_session_file_is_a_notification_and_changes_nothing(data, problem):
    s = small_state(v_m=0.07)
    s.run_to_convergence()
    before = {k: getattr(s, k) for k in ("case_name", *session.CONTROLS)}
    waves = s.waves
    seen = errors_of(s)
    assert not s.open_session(data, "bad.json")
    assert len(seen) >= 1 and problem in seen[0]
    assert {k: getattr(s, k) for k in before} == before and s.waves is waves


# ---------------------------------------------------------------------------------------
# Results kept per case; downloads


def test_switching_cases_keeps_each_cases_results():
    s = run_small(small_state(v_m=0.04), [Method.S1])
    waves, result = s.waves, s.results[Method.S1]
    s.case_name = "shear-5"
    assert s.waves == () and s.results == {}
    s.case_name = "beam-1d"
    assert s.waves is waves and s.results[Method.S1] is result and s.v_m == 0.04


def test_downloads_give_the_files_of_the_current_results():
    s = small_state()
    v = ExplorerView(state=s)
    files = v.files_view()
    pn.panel(files).get_root(Document())
    buttons = {b.css_classes[0]: b for b in files.select(pn.widgets.FileDownload)}
    assert buttons["dl-nroy"].disabled and buttons["dl-report"].disabled
    template = buttons["dl-template"].callback().getvalue().decode()
    assert template == measurements_template(s.case)
    run_small(s, [Method.S1])
    assert not buttons["dl-nroy"].disabled and not buttons["dl-predictions"].disabled
    # Plain CSV: pandas reads the downloads as they are (no comment lines).
    nroy = pd.read_csv(buttons["dl-nroy"].callback())
    assert list(nroy.columns) == ["wave", "l_cr [mm]", "E [GPa]", "implausibility"]
    assert set(nroy["wave"]) == {w.index for w in s.waves}
    assert nroy["implausibility"].max() <= s.threshold
    pred = pd.read_csv(buttons["dl-predictions"].callback())
    assert len(pred) == s.case.X_test.shape[0]                 # one method, one output
    assert pred["z_mean"].dtype.kind == "f" and set(pred["method"]) == {1}
    html = buttons["dl-report"].callback().getvalue().decode()
    assert html.startswith("<!DOCTYPE html>") and "<script src=" not in html
    doc = json.loads(buttons["dl-session"].callback().getvalue())
    assert doc["run"]["methods"]["1"]["metrics"] == s.results[Method.S1].metrics.as_dict()
    assert buttons["dl-report"].filename == "beam-1d_report.html"


# ---------------------------------------------------------------------------------------
# panel serve app/main.py --args --case my_case.toml


def test_case_files_given_to_the_server_join_the_case_list(tmp_path):
    from mdcore_app import main
    toml = main.Path(__file__).resolve().parent.parent / "examples" / "beam_lab" / "beam_lab.toml"
    view = main.create_app(["--case", str(toml)])
    s = view.state
    assert "beam-lab" in s.param.case_name.objects
    s.case_name = "beam-lab"
    s.param.update(**SMALL)
    run_small(s, [Method.S1])
    assert s.case.theta_names == ("E", "w0") and np.isfinite(s.results[Method.S1].metrics.lpl[0])
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[data]\nfile = 3\n', encoding="utf-8")
    cases_, errors = main.own_cases([bad, tmp_path / "missing.toml"])
    assert cases_ == [] and len(errors) == 2
    assert "bad.toml" in errors[0] and "file" in errors[0] and "does not exist" in errors[1]


# ---------------------------------------------------------------------------------------
# The same file again, the session you are on again (issue 40 item 3)


def test_the_same_file_again_and_the_open_session_again_keep_the_session_working():
    """Uploading a file of the same name replaces its case's data, and opening the session
    you are on reopens it: ``case`` never passes through None, so every view (the whole
    page is built here, watchers included) keeps drawing, and later actions work."""
    s = small_state()
    view = ExplorerView(state=s)
    view.__panel__()
    view.files_view()
    seen = errors_of(s)
    cases_seen = []
    s.param.watch(lambda e: cases_seen.append(e.new), "case")
    assert s.upload_measurements(lab_csv(shift=0.02).encode(), "lab.csv")
    quiet(run_small, s, [Method.S1])
    assert s.upload_measurements(lab_csv(shift=0.05).encode(), "lab.csv")   # new data
    assert s.case_name == "beam-1d · lab.csv" and s.waves == () and s.results == {}
    np.testing.assert_allclose(s.case.z_train, cases.load("beam-1d").z_train + 0.05,
                               rtol=0, atol=1e-12)
    quiet(run_small, s, [Method.S1])
    saved = s.session_json().encode()
    for _ in range(2):
        assert quiet(s.open_session, saved, "lab_session.json")
        assert "every metric equals the saved one" in s.status
    assert None not in cases_seen and seen == []
    assert list(s.param.case_name.objects).count("beam-1d · lab.csv") == 1
    s.case_name = "beam-2d"                       # and the session goes on
    s.case_name = "beam-1d · lab.csv"
    assert s.results and seen == []


def test_a_refused_session_leaves_no_case_behind():
    """A session file on uploaded data whose controls are refused adds no case to the
    list and changes nothing (before, the case stayed in the list)."""
    s = small_state()
    s.run_to_convergence()
    other = small_state()
    other.upload_measurements(lab_csv().encode(), "lab.csv")
    doc = json.loads(other.session_json())
    doc["controls"]["n_phi"] = 0
    objects, waves = list(s.param.case_name.objects), s.waves
    seen = errors_of(s)
    assert not s.open_session(json.dumps(doc).encode(), "lab_session.json")
    assert len(seen) == 1 and "N_φ" in seen[0]
    assert list(s.param.case_name.objects) == objects and s.case_name == "beam-1d"
    assert s.waves is waves


# ---------------------------------------------------------------------------------------
# The app's own limits, tighter than the library's (issue 40 item 11)


@pytest.mark.parametrize("name, value, words", [
    ("n_candidates", 1_000_001, "at most 1,000,000 candidates per wave"),
    ("n_candidates", 10_000_000, "the command line takes up to 10,000,000"),
    ("n_runs", 101, "at most 100 simulator runs per wave"),
    ("n_s", 1_001, "at most 1,000 θ samples and 1,000 φ per θ"),
    ("n_phi", 100_000, "10⁶ pairs"),
])
def test_the_app_refuses_more_work_than_its_limits_and_says_why(name, value, words):
    """The fields refuse values beyond the app's limits (the library takes 10⁷ candidates,
    10⁴ runs, 10⁵ × 10⁵ pairs) with a notification that says the limit and why; the
    session keeps its value. The limits themselves are accepted."""
    from mdcore_app.runs import KOH_CHAINS
    from mdcore_app.session_model import APP_MAX_CANDIDATES, APP_MAX_N_PHI, APP_MAX_N_S
    s = ExplorerState()
    view = ExplorerView(state=s)
    fields = {w.label: w for w in view._controls().select(pn.widgets.Widget)
              if hasattr(w, "label")}
    field = fields[s.param[name].label]
    before = getattr(s, name)
    seen = errors_of(s)
    field.value = value
    assert getattr(s, name) == before and field.value == before
    assert len(seen) == 1 and words in seen[0] and f"{value:,} is not allowed" in seen[0]
    s.param.update(n_candidates=APP_MAX_CANDIDATES, n_s=APP_MAX_N_S, n_phi=APP_MAX_N_PHI)
    assert max(c["n_iter"] for c in KOH_CHAINS.values()) <= 150_000 < 10**8


def test_a_session_file_beyond_the_app_limits_is_refused():
    doc = good_doc()
    doc["controls"]["n_candidates"] = 10_000_000         # the library's limit
    s = small_state()
    seen = errors_of(s)
    assert not s.open_session(json.dumps(doc).encode(), "big.json")
    assert len(seen) == 1 and "at most 1,000,000 candidates per wave" in seen[0]


def test_scenario_3_and_koh_on_many_training_rows_are_refused_before_they_run():
    """Each (θ, φ) pair of scenario 3 and each step of the KOH chain factorises an N × N
    covariance per output: on 300 training rows, the app refuses what would take it
    minutes to hours, at once and with what to change; the built-in cases run at the
    paper's sizes and chain."""
    from mdcore_app.session_model import work_problem
    lines = ["crack location,tip deflection,test"]
    rng = np.random.default_rng(0)
    lines += [f"{x:.6f},{1.0 + 0.01 * rng.standard_normal():.6f},0"
              for x in np.linspace(0.1, 0.5, 300)]
    lines += ["0.3,1.0,1", "0.4,1.1,1"]
    s = small_state()
    assert s.upload_measurements(("\n".join(lines) + "\n").encode(), "many.csv")
    seen = errors_of(s)
    s.scenarios, s.koh_chain = [Method.KOH], "paper"
    s.run_discrepancy()
    assert len(seen) == 1 and "KOH with a 150,000-step chain on 300 training rows" in seen[0]
    assert "fast chain" in seen[0] and s.results == {} and not s.busy
    s.param.update(scenarios=[Method.S3], n_s=1000, n_phi=1000)
    s.run_discrepancy()
    assert len(seen) == 2 and "Lower N_s × N_φ to at most 37,037" in seen[1]
    for name in cases.names():
        case = cases.load(name)
        for chain in ("fast", "paper"):
            big = ExplorerState(case_name=name, koh_chain=chain, paper_sizes=True)
            assert work_problem(case, big.method_settings(), [Method.S3, Method.KOH]) is None
