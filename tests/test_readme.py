"""The README's Python example runs as written, and its commands are the ones CI uses."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_readme_example_runs():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    assert len(code.strip().splitlines()) <= 12
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert namespace["pred"].z_mean.shape == (200, 1)
    result = namespace["result"]
    assert result.metrics.nmse_z[0] < 3.0 and result.importance.k_hat[0] < 0.7


def test_ci_runs_the_readme_test_command_verbatim():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    commands = re.findall(r"```bash\n(.*?)\n```", text, re.S)
    assert len(commands) >= 2
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert commands[1].strip() in ci.splitlines()


def test_your_own_data_commands_run_as_written(tmp_path, monkeypatch, capsys):
    """The "Your own data" commands, verbatim: the CLI run writes its files, and the
    app's --args give the case list the case."""
    import json
    import shlex

    from mdcore._cli import main

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text[text.index("## Your own data"):]
    block = re.search(r"```console\n(.*?)```", section, re.S).group(1)
    commands = [shlex.split(line) for line in block.strip().splitlines()]
    assert [c[:3] for c in commands] == [["python", "-m", "mdcore"], ["panel", "serve",
                                                                      "app/main.py"]]
    monkeypatch.chdir(tmp_path)                      # outputs land here; inputs from ROOT
    run = [str(ROOT / a) if a.startswith("examples/") else a for a in commands[0][3:]]
    assert main(run) == 0
    assert [p.name for p in tmp_path.iterdir()] == ["results"]    # one folder, made by the run
    assert (tmp_path / "results" / "report.html").stat().st_size > 10_000
    assert json.loads((tmp_path / "results" / "run.json").read_text())["case"] == "beam-lab"
    assert (tmp_path / "results" / "predictions.csv").exists()
    assert "wrote results/report.html" in capsys.readouterr().out
    serve = commands[1]                              # this machine only
    assert serve[serve.index("--address") + 1] == "127.0.0.1"

    pytest.importorskip("panel")
    from mdcore_app import main as app_main
    args = commands[1][commands[1].index("--args") + 1:]
    view = app_main.create_app([str(ROOT / a) if a.startswith("examples/") else a
                                for a in args])
    assert "beam-lab" in view.state.param.case_name.objects
