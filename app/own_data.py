"""A session's own data in and its results out: uploaded measurements, saved sessions,
the CLI's ``CaseRun``, and the "Things to try" cards."""

from __future__ import annotations

import json
from functools import partial

import param

from mdcore import _cases as cases
from mdcore._case_file import with_measurements
from mdcore._pipeline import Method, Settings

from . import session
from .case_model import OwnCase
from .experiments import EXPERIMENTS, METHOD_FACTS
from .runs import DiscrepancyModel, discrepancy_job, method_order
from .session_model import APP_LIMITS, allowed_values


class OwnDataModel(DiscrepancyModel):
    """Uploads and session files in; a ``CaseRun`` and session JSON out; the "Things to
    try" cards."""

    card = param.String(default="", doc="The last card run and where to look, shown above "
                                        "every tab until another case is chosen.")

    @param.depends("case_name", watch=True)
    def _forget_card(self):
        self.card = ""

    def upload_measurements(self, data: bytes, filename: str) -> bool:
        """Use uploaded measurements (the layout of :func:`mdcore.measurements_template`)
        with the current case's simulator, as a new case; whether it was added. The file
        is only parsed; each problem is one notification, and the session keeps its case."""
        base = self.base_case_name()
        try:
            text = session.decode_upload(data, filename, kind="measurements CSV")
            case = with_measurements(cases.load(base, seed=0), text, source=filename)
        except ValueError as exc:
            for problem in getattr(exc, "problems", (str(exc),)):
                self.report_error(problem)
            return False
        self._add_case(OwnCase(case, base, text, filename))
        return True

    def _add_case(self, own: OwnCase) -> None:
        """Add (or replace) a session case and select it."""
        name = own.case.name
        self._kept.pop(name, None)
        self._own[name] = own
        self.param.case_name.objects = list(cases.names()) + list(self._own)
        if self.case_name == name:                   # replaced: load the new data
            self._load_case(replace=True)
        else:
            self.case_name = name

    def case_run(self):
        """The history match and results as the CLI's :class:`~mdcore.CaseRun`, or None
        before any result."""
        from mdcore._reproduce import CaseRun
        if not self.results or self.history_match is None:
            return None
        results = tuple(self.results[m] for m in sorted(self.results, key=method_order))
        return CaseRun(self.case, self.history_match, self.method_settings(), self.seed,
                       results)

    def session_json(self) -> str:
        """The session as JSON (the layout of :mod:`mdcore_app.session`)."""
        own = self._own.get(self.case_name)
        own = OwnCase(None) if own is None else own
        controls = {k: getattr(self, k) for k in (*session.CONTROLS, *session.OPTIONAL_CONTROLS)}
        controls["scenarios"] = [m.value for m in sorted(self.scenarios, key=method_order)]
        run = self.case_run()
        doc = session.session_document(
            case_name=self.case_name, based_on=own.based_on,
            measurements_csv=own.measurements_csv, measurements_file=own.measurements_file,
            controls=controls,
            n_waves=len(self.waves) if self._problem_key == self._settings_key() else 0,
            run=None if run is None else run.to_dict())
        return json.dumps(doc, indent=1, allow_nan=False)

    def set_controls(self, controls: dict, filename: str) -> Settings:
        """Set a session file's ``controls`` in the file's order (a preset first sets what
        it implies) and return the settings they make; a SessionError names the first
        control outside its parameter's bounds or choices."""
        self._restoring = True
        try:
            for k, v in controls.items():
                try:
                    setattr(self, k, v)
                except ValueError:                       # the parameter's own bounds or choices
                    why = f" {APP_LIMITS[k]}" if k in APP_LIMITS else ""
                    raise session.SessionError([
                        f"{filename}: controls.{k} = {v!r} is not allowed for "
                        f"{self.param[k].label} ({allowed_values(self.param[k])}).{why}"]
                    ) from None
        finally:
            self._restoring = False
        return self.method_settings()

    def open_session(self, data: bytes, filename: str) -> bool:
        """Restore a saved session (case, uploaded data, controls; waves and methods
        recomputed and checked against the saved metrics); whether it was accepted. The
        file is checked in full, its controls on a scratch state, before anything changes:
        each problem is one notification and the session keeps its state."""
        before = {k: getattr(self, k)
                  for k in ("case_name", *session.CONTROLS, *session.OPTIONAL_CONTROLS)}
        try:
            doc = session.parse_session(
                session.decode_upload(data, filename, kind="session JSON"), filename)
            case = doc["case"]
            controls = dict(doc["controls"])
            controls["scenarios"] = [Method.parse(v) for v in controls["scenarios"]]
            type(self)().set_controls(controls, filename)   # refused before any change
            own = None
            if case["measurements_csv"] is not None:
                base = case["based_on"]
                if base not in cases.names():
                    raise session.SessionError([f"{filename}: case.based_on must be one of "
                                                f"{list(cases.names())}; found {base!r}."])
                own = with_measurements(cases.load(base, seed=0), case["measurements_csv"],
                                        source=case["measurements_file"] or "measurements.csv")
            elif case["name"] not in self.param.case_name.objects:
                raise session.SessionError([
                    f"{filename}: the case {case['name']!r} is not in this app (it has "
                    f"{', '.join(self.param.case_name.objects)}); start the app with "
                    f"`--args --case <its case file>.toml` to add it."])
            if own is not None:
                self._add_case(OwnCase(own, case["based_on"], case["measurements_csv"],
                                       case["measurements_file"]))
            else:
                self.case_name = case["name"]
            settings = self.set_controls(controls, filename)
        except ValueError as exc:
            self._restoring = True
            try:
                self.param.update(**before)              # the session keeps its state
            finally:
                self._restoring = False
            for problem in getattr(exc, "problems", (str(exc),)):
                self.report_error(problem)
            return False
        saved = (doc["run"] or {}).get("methods")
        if doc["n_waves"] == 0:
            self.status = f"Session opened from {filename} (it had no waves yet)."
            return True
        if not saved:
            self._jobs.submit("waves", partial(discrepancy_job, self._plan(
                settings, n_waves=doc["n_waves"], waves_only=True)), self._apply)
            return True
        self._jobs.submit("session", partial(discrepancy_job, self._plan(
            settings, n_waves=doc["n_waves"], expected=saved)), self._apply)
        return True

    def try_experiment(self, key: str) -> None:
        """Run the "Things to try" card ``key``: set all its controls (so earlier cards never
        matter), say where to look in the card line above the tabs (:attr:`card`), and run
        the waves, and the methods when its promise is about them."""
        exp = next((e for e in EXPERIMENTS if e.key == key), None)
        if exp is None:
            self.report_error(f"Unknown experiment {key!r}; choose one of "
                              f"{[e.key for e in EXPERIMENTS]}.")
            return
        before = self.case_name
        settings = self.set_controls(exp.settings, f"the card {exp.title!r}")
        moved = (f" (the card switched the case from {before} to {self.case_name})"
                 if self.case_name != before else "")
        self.card = f"{exp.title}{moved} — look at: {exp.look}"
        if exp.expect.keys() & METHOD_FACTS:
            label, compute = "discrepancy", partial(discrepancy_job, self._plan(settings))
        else:
            label, compute = "waves", partial(self._wave_job, True)
        self._jobs.submit(label, compute, self._apply)     # the card line says where to look

