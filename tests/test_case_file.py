"""Own cases from TOML + CSV + a simulator: the worked example, and malformed files."""

import re
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest

from mdcore._case_file import CaseFileError, load_case_file

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "beam_lab"

SIMULATOR = '''
import numpy as np

def linear(X, theta):
    theta = np.atleast_2d(theta)
    return (theta[:, :1] * X[None, :, 0] + theta[:, 1:2])[..., None]

def wrong_shape(X, theta):
    return np.zeros((len(X),))

def broken(X, theta):
    raise RuntimeError("licence server unreachable")
'''

CSV = """# a line of provenance
x,y,test
0.0,0.10,0
0.0,0.12,0
0.5,0.61,0
0.5,0.59,0
1.0,1.11,0
1.0,1.09,0
0.25,0.35,1
0.75,0.86,1
"""

TOML = """
name = "line"
[data]
file = "data.csv"
inputs = ["x"]
outputs = ["y"]
test_column = "test"
[simulator]
function = "toy_sim:linear"
path = "."
[[parameters]]
name = "slope"
lower = 0.0
upper = 2.0
[[parameters]]
name = "intercept"
lower = -1.0
upper = 1.0
[history_matching]
V_m = [0.01]
"""


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "toy_sim.py").write_text(SIMULATOR, encoding="utf-8")
    (tmp_path / "data.csv").write_text(CSV, encoding="utf-8")
    return tmp_path


def write(folder, toml=TOML, csv=None):
    path = folder / "case.toml"
    path.write_text(textwrap.dedent(toml), encoding="utf-8")
    if csv is not None:
        (folder / "data.csv").write_text(csv, encoding="utf-8")
    return path


def test_a_valid_case_file_builds_a_case(folder):
    case = load_case_file(write(folder))
    assert case.name == "line" and case.theta_names == ("slope", "intercept")
    assert case.X_train.shape == (6, 1) and case.X_test.shape == (2, 1)
    np.testing.assert_allclose(case.z_test[:, 0], [0.35, 0.86])
    # No noise_var given: the pooled replicate variance (each pair differs by 0.02).
    np.testing.assert_allclose(case.noise_var, [0.0002], rtol=1e-9)
    np.testing.assert_allclose(case.theta_prior.mean, [1.0, 0.0])
    np.testing.assert_allclose(case.theta_prior.var, [0.25, 0.25])
    assert case.theta_true is None and case.true_delta(case.X_test) is None
    np.testing.assert_allclose(case.simulate(case.X_test, [[1.0, 0.1]])[0, :, 0], [0.35, 0.85])
    assert case.initial_design.shape == (20, 2) and not case.stand_in
    np.testing.assert_array_equal(case.V_m_length, [0.0])
    assert case.V_m_corr is None
    correlated = load_case_file(write(folder, TOML.replace(
        "V_m = [0.01]", "V_m = [0.01]\nV_m_length = [0.25]\nV_m_corr = [[1.0]]")))
    np.testing.assert_array_equal(correlated.V_m_length, [0.25])
    np.testing.assert_array_equal(correlated.V_m_corr, [[1.0]])


def test_the_worked_example_runs_end_to_end(tmp_path):
    from mdcore._export import write_tables
    from mdcore._pipeline import Settings
    from mdcore._reproduce import run_case
    case = load_case_file(EXAMPLE / "beam_lab.toml")
    assert case.theta_names == ("E", "w0") and case.X_test.shape == (9, 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = run_case(case, settings=Settings(n_s=40, n_phi=40, proposal="adaptive"))
    assert run.truth_in_nroy is True
    assert all(r.metrics.nmse_z[0] < 1.0 for r in run.results)     # z within 1 % NMSE
    nroy, _, pred, _ = write_tables(run, tmp_path)
    lines = pred.read_text(encoding="utf-8").splitlines()
    assert lines[0].startswith("method,output,position_m,z_observed")     # m said once
    assert len(lines) == 1 + 3 * 9
    assert nroy.read_text(encoding="utf-8").splitlines()[0] == "wave,E [GPa],w0 [mm],implausibility"


BAD = [
    ("missing file", lambda f: f / "nope.toml", "does not exist"),
    ("not TOML", lambda f: write(f, "name = [unclosed"), "not valid TOML"),
    ("bad name", lambda f: write(f, TOML.replace('name = "line"', 'name = "a b"')),
     r"name must be a string matching"),
    ("no [data]", lambda f: write(f, TOML.split("[data]")[0] + "[simulator]"
                                  + TOML.split("[simulator]")[1]),
     r"data must be a table \(\[data\]\); found None"),
    ("misspelt table", lambda f: write(f, TOML.replace("[data]", "[datum]")),
     r"the top level has unknown key\(s\) 'datum' \(did you mean 'data'\?\)"),
    ("misspelt key", lambda f: write(f, TOML.replace('file = "data.csv"', 'fiel = "data.csv"')),
     r"\[data\] has unknown key\(s\) 'fiel' \(did you mean 'file'\?\); the keys allowed "
     r"there are \['file', 'inputs'"),
    ("missing CSV column", lambda f: write(f, TOML.replace('outputs = ["y"]', 'outputs = ["w"]')),
     r"column\(s\) \['w'\] not found"),
    ("non-numeric cell", lambda f: write(f, csv=CSV.replace("0.59", "n/a")),
     r"data.csv line 6, column 'y': 'n/a' is not a number"),
    ("bad test flag", lambda f: write(f, csv=CSV.replace("0.86,1", "0.86,2")),
     r"column 'test' must be 0 \(training row\) or 1"),
    ("no test rows", lambda f: write(f, csv=CSV.replace(",1\n", ",0\n")),
     r"column 'test' marks 8 training row\(s\) \(0\) and 0 test row\(s\) \(1\); at least 3 "
     "training rows are needed to fit the discrepancy GP and 2 test rows to score it"),
    ("one test row", lambda f: write(f, csv=CSV.replace("0.86,1", "0.86,0")),
     r"marks 7 training row\(s\) \(0\) and 1 test row\(s\) \(1\); .* Mark more rows"),
    ("equal test rows", lambda f: write(f, csv=CSV.replace("0.86,1", "0.35,1")),
     r"every test row \(column 'test' = 1\) has the same 'y'; the NMSE divides by its "
     "variance"),
    ("huge value", lambda f: write(f, csv=CSV.replace("0.59", "1e300")),
     r"data.csv line 6, column 'y': '1e300' is larger in magnitude than 1e\+30, whose square "
     r"\(a variance\) overflows; express the column in other units"),
    ("noise needed", lambda f: write(f, csv=CSV.replace("1.0,1.09,0\n", "")),
     "noise_var is required"),
    ("bad noise", lambda f: write(f, TOML.replace('test_column = "test"',
                                                  'test_column = "test"\nnoise_var = [-1.0]')),
     r"\[data\] noise_var must be a list of 1 positive numbers"),
    ("bad import path", lambda f: write(f, TOML.replace("toy_sim:linear", "toy_sim.linear")),
     r"\[simulator\] function must be 'package.module:function'; found 'toy_sim.linear'"),
    ("no module", lambda f: write(f, TOML.replace("toy_sim:linear", "nosuchmod:linear")),
     "cannot import module 'nosuchmod'"),
    ("no function", lambda f: write(f, TOML.replace("toy_sim:linear", "toy_sim:quadratic")),
     "has no function 'quadratic'"),
    ("wrong shape", lambda f: write(f, TOML.replace("toy_sim:linear", "toy_sim:wrong_shape")),
     r"toy_sim:wrong_shape must return shape \(n_theta, N, n_out\) = \(1, 6, 1\) for one θ at "
     r"the 6 training inputs; it returned \(6,\)"),
    ("simulator raises", lambda f: write(f, TOML.replace("toy_sim:linear", "toy_sim:broken")),
     "failed at the centre of the parameter box .* licence server unreachable"),
    ("upper <= lower", lambda f: write(f, TOML.replace("upper = 2.0", "upper = -2.0")),
     r"\[parameters 1\] upper must be greater than lower = 0"),
    ("no parameters", lambda f: write(f, TOML.split("[[parameters]]")[0]
                                      + "[history_matching]\nV_m = [0.01]\n"),
     r"\[\[parameters\]\] must be one or more tables"),
    ("duplicate names", lambda f: write(f, TOML.replace('name = "intercept"', 'name = "slope"')),
     "names must be distinct"),
    ("V_m size", lambda f: write(f, TOML.replace("V_m = [0.01]", "V_m = [0.01, 0.02]")),
     r"\[history_matching\] V_m must be a list of 1 positive numbers"),
    ("V_m text", lambda f: write(f, TOML.replace("V_m = [0.01]", 'V_m = "small"')),
     r"V_m must be a list of 1 positive numbers .*; found 'small'"),
    ("V_m_length negative", lambda f: write(f, TOML.replace("V_m = [0.01]",
                                                            "V_m = [0.01]\nV_m_length = [-1]")),
     r"\[history_matching\] V_m_length must be a list of 1 numbers ≥ 0"),
    ("V_m_corr shape", lambda f: write(f, TOML.replace("V_m = [0.01]",
                                                       "V_m = [0.01]\nV_m_corr = [1.0]")),
     r"\[history_matching\] V_m_corr must be a list of 1 rows of 1 numbers"),
    ("V_m_corr diagonal", lambda f: write(f, TOML.replace("V_m = [0.01]",
                                                          "V_m = [0.01]\nV_m_corr = [[2.0]]")),
     r"\[history_matching\] V_m_corr must be a symmetric \(1, 1\) correlation matrix with "
     "ones on its diagonal"),
    ("partial truth", lambda f: write(f, TOML.replace("upper = 2.0", "upper = 2.0\ntrue = 1.0")),
     "true must be given for every parameter or for none"),
]


@pytest.mark.parametrize("kind, make, match", BAD, ids=[b[0] for b in BAD])
def test_malformed_case_files_name_the_problem(folder, capsys, kind, make, match):
    path = make(folder)
    with pytest.raises(CaseFileError, match=match) as info:
        load_case_file(path)
    # Bad input for the command line too: exit 2 and the same message (a ValueError).
    from mdcore._cli import main
    assert main(["run", str(path)]) == 2
    assert capsys.readouterr().err == f"error: {info.value}\n"
    if kind != "missing file":
        assert str(path.parent) in str(info.value) or "data.csv" in str(info.value)


SECRET = "root:$6$SECRET-HASH:19000:0:99999:7:::\nadmin = \"SECRET-PASSWORD\"\n"
FOREIGN = [
    ("data file is another file", lambda f: (f / "passwd").write_text(SECRET) and write(
        f, TOML.replace('file = "data.csv"', 'file = "passwd"')),
     r"passwd line 1: column\(s\) \['x', 'test', 'y'\] not found in a header with none of "
     r"them \(is this the measurements file\?\)"),
    ("case file is another file", lambda f: (f / "passwd").write_text(SECRET) and f / "passwd",
     r"passwd: not valid TOML \(Expected '=' after a key"),
    ("case file is another TOML", lambda f: write(f, 'admin = "SECRET-PASSWORD"\n'
                                                     '[SECRET-TABLE]\nkey = 1\n'),
     r"case\.toml: not a case file: none of its top-level keys is one of \['name', "),
    ("arrays nested deeply", lambda f: write(f, "name = " + "[" * 5000 + "]" * 5000),
     r"case\.toml: not a case file: its arrays or tables are nested too deeply to read"),
    ("tables nested deeply", lambda f: write(f, "name = " + "{a = " * 2000 + "1" + "}" * 2000),
     r"case\.toml: not a case file: its arrays or tables are nested too deeply to read"),
    ("a folder", lambda f: f, r"case file '.*' is a folder; give the TOML case file itself"),
]


@pytest.mark.parametrize("kind, make, match", FOREIGN, ids=[b[0] for b in FOREIGN])
def test_errors_name_the_file_and_quote_nothing_of_a_foreign_one(folder, capsys, kind, make,
                                                                 match):
    """A case file or CSV path that points at some other file (a password file, another
    TOML, a folder): the command line says which file and what is wrong, exit 2, and no
    line of that file appears in the message (issue 40, item 11)."""
    from mdcore._cli import main
    path = make(folder)
    assert main(["run", str(path)]) == 2
    err = capsys.readouterr().err
    assert re.search(match, err), err
    assert "SECRET" not in err and "Traceback" not in err and len(err) < 600


def test_a_case_file_has_at_most_the_row_limits(folder):
    """The measurements of a case file have at most mdcore._cases.MAX_ROWS rows, of which
    at most MAX_TRAINING_ROWS training rows; at the limits the case loads."""
    from mdcore._case_file import MAX_TRAINING_ROWS
    from mdcore._cases import MAX_ROWS

    def rows(n, flag):
        return "".join(f"{0.3 + 0.4 * i / n:.6f},{0.5 + 0.1 * i / n:.6f},{flag}\n"
                       for i in range(n))

    header = CSV.split("\n", 2)[:2]
    head = "\n".join(header) + "\n"
    noise = TOML.replace('test_column = "test"', 'test_column = "test"\nnoise_var = [1e-4]')
    case = load_case_file(write(folder, noise, csv=head + rows(MAX_TRAINING_ROWS, 0)
                                + rows(MAX_ROWS - MAX_TRAINING_ROWS, 1)))
    assert case.X_train.shape[0] == MAX_TRAINING_ROWS
    with pytest.raises(CaseFileError, match=rf"{MAX_TRAINING_ROWS + 1:,} training rows; at "
                                            rf"most {MAX_TRAINING_ROWS:,}"):
        load_case_file(write(folder, noise, csv=head + rows(MAX_TRAINING_ROWS + 1, 0)
                             + rows(10, 1)))
    with pytest.raises(CaseFileError, match=rf"more than {MAX_ROWS:,} data rows"):
        load_case_file(write(folder, noise, csv=head + rows(100, 0) + rows(MAX_ROWS, 1)))
