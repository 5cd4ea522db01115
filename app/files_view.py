"""The Files tab: your measurements in, a saved session in, results out."""

from __future__ import annotations

import io
import re

import panel as pn
import param

from mdcore._case_file import MAX_TRAINING_ROWS, TEST_COLUMN, measurements_template
from mdcore._cases import MAX_ROWS
from mdcore._export import nroy_csv, predictions_csv

from .markup import markdown_text
from .report import report_html
from .session import MAX_UPLOAD_BYTES, megabytes
from .state import ExplorerState
from .upload import FileUpload


class FilesView(pn.viewable.Viewer):
    """Drop areas for measurements and session files, and the downloads."""

    state = param.ClassSelector(class_=ExplorerState)

    def __init__(self, **params):
        super().__init__(**params)
        self._layout = self._build()

    def __panel__(self):
        return self._layout

    def _slug(self) -> str:
        return re.sub(r"[^A-Za-z0-9_.-]+", "_", self.state.case_name).strip("_")

    def _dropper(self, accept: str, handler, css: str, prompt: str) -> FileUpload:
        """A drop area calling ``handler(data, filename) -> bool`` once per file (sent in
        counted chunks, at most MAX_UPLOAD_BYTES); a file it refuses is marked refused
        with its first problem (every problem is also a notification)."""
        s = self.state

        def take(data: bytes, filename: str) -> str | None:
            problems: list[str] = []
            watcher = s.param.watch(lambda _: problems.append(s.error), "n_errors")
            try:
                taken = handler(data, filename)
            finally:
                s.param.unwatch(watcher)
            if taken:
                return None
            more = f" (and {len(problems) - 1} more: see the messages)" if problems[1:] else ""
            return (problems[0] if problems else "It was not taken.") + more

        return FileUpload(take=take, refuse=s.report_error, accept=accept, prompt=prompt,
                          max_bytes=MAX_UPLOAD_BYTES, css_classes=[css], margin=(5, 10),
                          sizing_mode="stretch_width")

    @param.depends("state.case")
    def _upload_help(self):
        s = self.state
        c = s.case
        columns = ", ".join(f"<code>{markdown_text(n)}</code>"
                            for n in (*c.x_names, *c.output_names, TEST_COLUMN))
        return pn.pane.Markdown(
            "#### Your measurements\nA CSV for the simulator of the case selected on the left "
            f"(now {markdown_text(s.base_case_name())}): a header row with the columns "
            f"{columns} (`{TEST_COLUMN}`: 1 = held-out test row, 0 = training row), one row per "
            "observation, replicates as repeated rows, `#` lines as comments. Start from "
            f"the template. At most {MAX_ROWS:,} data rows, of which at most "
            f"{MAX_TRAINING_ROWS:,} training rows, and {megabytes(MAX_UPLOAD_BYTES)}; the "
            "file is only read, never run. It becomes a new case of this session, named "
            "after the file.",
            css_classes=["upload-help"])

    def _build(self):
        """The Files tab: your measurements in, a saved session in, results out."""
        s = self.state

        def nroy():
            hm = s.history_match
            return None if hm is None else nroy_csv(hm, s.case.theta_names, s.case.theta_units)

        def with_run(write):
            return lambda: None if (run := s.case_run()) is None else write(run)

        # key: label, file name ending, the text (None: nothing to give yet)
        made = {"template": ("Template CSV (this case's data)", "_measurements.csv",
                             lambda: measurements_template(s.case)),
                "session": ("Session (JSON)", "_session.json", s.session_json),
                "nroy": ("NROY samples (CSV)", "_nroy.csv", nroy),
                "predictions": ("Predictions and δ bands (CSV)", "_predictions.csv",
                                with_run(predictions_csv)),
                "report": ("Report (HTML, opens offline)", "_report.html",
                           with_run(report_html))}

        def download(key):
            """A button whose file is made when pressed."""
            label, _, make = made[key]
            return pn.widgets.FileDownload(
                callback=lambda: io.BytesIO((make() or "").encode("utf-8")), label=label,
                color="primary", variant="outline", css_classes=[f"dl-{key}"],
                sizing_mode="stretch_width")

        downloads = {key: download(key) for key in made}

        def refresh(*_):
            for key, (_, ending, _) in made.items():
                downloads[key].filename = self._slug() + ending
            downloads["nroy"].disabled = not s.waves
            downloads["predictions"].disabled = downloads["report"].disabled = not s.results

        s.param.watch(refresh, ["case_name", "waves", "results"])
        refresh()
        return pn.Column(
            self._upload_help,
            pn.Row(self._dropper(".csv,text/csv", s.upload_measurements, "upload-csv",
                                 "Drop your measurements CSV here, or click to choose it."),
                   downloads["template"], sizing_mode="stretch_width"),
            pn.pane.Markdown("#### Results out\nCSV tables (every wave's NROY samples with "
                             "their implausibility; z and δ means and sds per method at the "
                             "test inputs), a report with the plots that opens offline, and "
                             "the session: settings and metrics as JSON, no pickle."),
            pn.Row(downloads["nroy"], downloads["predictions"], sizing_mode="stretch_width"),
            pn.Row(downloads["report"], downloads["session"], sizing_mode="stretch_width"),
            pn.pane.Markdown("#### Open session…\nA session JSON saved here. Its case, "
                             "settings, waves and methods are recomputed (every step is "
                             "seeded) and checked against the saved metrics; the status line "
                             "says whether they agree."),
            self._dropper(".json,application/json", s.open_session, "open-session",
                          "Drop a session JSON here, or click to choose it."),
            sizing_mode="stretch_width", max_width=900)

