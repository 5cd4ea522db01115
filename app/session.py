"""Saved sessions and uploaded files of the app: JSON in and out, checked, never pickled.

A session file is JSON with a versioned layout::

    {"schema": "mdcore-session", "schema_version": 1, "mdcore_version": "...",
     "case": {"name": ..., "based_on": null | built-in case, "measurements_csv": null | text,
              "measurements_file": null | file name},
     "controls": {"preset", "v_m", "threshold", "rule", "n_runs", "n_candidates", "max_waves",
                  "convergence_ratio", "n_s", "n_phi", "scenarios", "koh_chain",
                  "proposal", "seed", "band"},
     "n_waves": int,
     "run": null | the layout of ``python -m mdcore reproduce --json`` (the metrics)}

Opening one sets the controls and recomputes the waves and methods (every step is seeded;
:func:`compare_metrics` checks the numbers). Uploaded data travel inside the file. Whatever
a browser sends goes through :func:`decode_upload` (a size cap, UTF-8) and is then only
parsed (``json.loads``, :mod:`csv`): never run, imported or unpickled.
"""

from __future__ import annotations

import json
import math
import sys
from typing import Any

import mdcore
from mdcore._pipeline import Method, MethodResult

SCHEMA, SCHEMA_VERSION = "mdcore-session", 1
#: Largest file the app accepts from a browser (bytes), counted as the chunks arrive
#: (:mod:`.upload`) and in :func:`decode_upload`: far above the row limit's 60 kB.
MAX_UPLOAD_BYTES = 5_000_000
#: The state's parameters a session file stores, and the JSON types each must have.
CONTROLS: dict[str, tuple[type, ...]] = {
    "preset": (str,), "v_m": (int, float), "threshold": (int, float), "rule": (str,),
    "n_runs": (int,), "n_candidates": (int,), "max_waves": (int,),
    "convergence_ratio": (int, float), "n_s": (int,), "n_phi": (int,), "scenarios": (list,),
    "koh_chain": (str,), "proposal": (str,), "seed": (int,), "band": (int,)}
#: Controls a session file may leave out (files saved before they existed), with defaults.
OPTIONAL_CONTROLS: dict[str, tuple[tuple[type, ...], object]] = {
    "v_m_length": ((int, float), 0.0)}
#: Relative difference below which a recomputed metric counts as the saved one.
RTOL = 1e-9


class SessionError(ValueError):
    """A file the app cannot take; ``problems`` lists what is wrong, one sentence each."""

    def __init__(self, problems: list[str]):
        self.problems = tuple(problems)
        super().__init__(" ".join(self.problems))


def megabytes(n: int) -> str:
    """``n`` bytes for messages: decimal megabytes from 0.1 MB ("5 MB", "6.2 MB"), else
    bytes ("1,001 bytes")."""
    return f"{n / 1e6:.1f}".removesuffix(".0") + " MB" if n >= 100_000 else f"{n:,} bytes"


def decode_upload(data: bytes, filename: str, *, kind: str) -> str:
    """The text of an uploaded file ``data``; a SessionError naming ``filename`` and the
    ``kind`` of file expected ("session JSON") if it is empty, larger than
    :data:`MAX_UPLOAD_BYTES` or not UTF-8."""
    if not isinstance(data, bytes | bytearray) or not data:
        raise SessionError([f"{filename}: the file is empty; choose a {kind}."])
    if len(data) > MAX_UPLOAD_BYTES:
        raise SessionError([f"{filename} is {len(data):,} bytes, more than the "
                            f"{megabytes(MAX_UPLOAD_BYTES)} limit ({MAX_UPLOAD_BYTES:,} bytes) "
                            f"for a {kind}."])
    try:
        return bytes(data).decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise SessionError([f"{filename}: not UTF-8 text ({exc.reason} at byte {exc.start}); "
                            f"a {kind} must be saved as UTF-8."]) from None


def parse_session(text: str, filename: str = "session.json") -> dict[str, Any]:
    """A session file's JSON, every key of the layout (module doc) present and of its type;
    else a SessionError listing every problem (not JSON, another schema or a newer version,
    a missing key, a value of the wrong type)."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SessionError([f"{filename}: not valid JSON (line {exc.lineno}, column "
                            f"{exc.colno}: {exc.msg})."]) from None
    except RecursionError:
        raise SessionError([f"{filename}: not a session file: its JSON is nested too deeply "
                            "to read (a session file is nested three levels deep). Save "
                            "one with “Save session”."]) from None
    except ValueError:                            # an integer of more than 4,300 digits
        raise SessionError([f"{filename}: not a session file: a number in it has more "
                            f"digits than Python reads ({sys.get_int_max_str_digits():,}). "
                            "Save one with “Save session”."]) from None
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
        found = doc.get("schema") if isinstance(doc, dict) else type(doc).__name__
        raise SessionError([f"{filename}: not an mdcore session (expected \"schema\": "
                            f"{SCHEMA!r}; found {found!r}). Save one with “Save session”."])
    version = doc.get("schema_version")
    if not isinstance(version, int) or not 1 <= version <= SCHEMA_VERSION:
        raise SessionError([f"{filename}: schema_version {version!r} is not supported; this "
                            f"app reads versions 1 to {SCHEMA_VERSION}."])
    problems = []
    case = doc.get("case")
    if not isinstance(case, dict) or not isinstance(case.get("name"), str):
        problems.append(f"{filename}: \"case\" must be an object with a \"name\" string; "
                        f"found {case!r}.")
    else:
        for k in ("based_on", "measurements_csv", "measurements_file"):
            if case.get(k) is not None and not isinstance(case[k], str):
                problems.append(f"{filename}: case.{k} must be a string or null; found "
                                f"{type(case[k]).__name__}.")
    controls = doc.get("controls")
    if not isinstance(controls, dict):
        problems.append(f"{filename}: \"controls\" must be an object; found {controls!r}.")
    else:
        for k in controls.keys() - CONTROLS.keys() - OPTIONAL_CONTROLS.keys():
            problems.append(f"{filename}: controls.{k} is not a control of this app (it has "
                            f"{', '.join([*CONTROLS, *OPTIONAL_CONTROLS])}).")
        for k, (_types, default) in OPTIONAL_CONTROLS.items():
            controls.setdefault(k, default)
        kinds = {**CONTROLS, **{k: t for k, (t, _) in OPTIONAL_CONTROLS.items()}}
        for k, types in kinds.items():
            v = controls.get(k)
            if v is None:
                problems.append(f"{filename}: controls.{k} is missing.")
            elif isinstance(v, bool) or not isinstance(v, types):
                problems.append(f"{filename}: controls.{k} must be "
                                f"{' or '.join(t.__name__ for t in types)}; found {v!r}.")
            elif isinstance(v, float) and not math.isfinite(v):
                problems.append(f"{filename}: controls.{k} must be finite; found {v!r}.")
    n_waves = doc.get("n_waves")
    if isinstance(n_waves, bool) or not isinstance(n_waves, int) or n_waves < 0:
        problems.append(f"{filename}: \"n_waves\" must be a whole number ≥ 0; found "
                        f"{n_waves!r}.")
    run = doc.get("run")
    if run is not None and not (isinstance(run, dict) and isinstance(run.get("methods"), dict)):
        problems.append(f"{filename}: \"run\" must be null or an object with \"methods\".")
    if problems:
        raise SessionError(problems)
    return doc


def session_document(*, case_name: str, based_on: str | None, measurements_csv: str | None,
                     measurements_file: str | None, controls: dict, n_waves: int,
                     run: dict | None) -> dict[str, Any]:
    """The JSON document of a session (layout in the module doc)."""
    return {"schema": SCHEMA, "schema_version": SCHEMA_VERSION,
            "mdcore_version": mdcore.__version__,
            "case": {"name": case_name, "based_on": based_on,
                     "measurements_csv": measurements_csv,
                     "measurements_file": measurements_file},
            "controls": controls, "n_waves": int(n_waves), "run": run}


def _close(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    return math.isclose(float(a), float(b), rel_tol=RTOL, abs_tol=1e-12)


def compare_metrics(saved: dict, results: dict[Method, MethodResult]) -> str:
    """A status line saying whether the recomputed ``results`` reproduce the ``saved``
    metrics (a session file's ``run["methods"]``) to :data:`RTOL`, or the first that differ."""
    differ, missing = [], []
    for value, entry in saved.items():
        method = Method.parse(value)
        if method not in results:
            missing.append(method.label)
            continue
        now = results[method].metrics.as_dict()
        for name, old in (entry.get("metrics") or {}).items():
            if name in now and not _close(old, now[name]):
                differ.append(f"{method.label} {name}: saved {old}, now {now[name]}")
    labels = ", ".join(Method.parse(v).label for v in saved)
    if not differ and not missing:
        return (f"Session restored: {labels} recomputed, and every metric equals the saved "
                f"one (to {RTOL:g} relative).")
    text = f"Session restored, but {len(differ)} metric(s) differ from the saved ones"
    if missing:
        text += f" and {', '.join(missing)} did not run"
    return text + ": " + "; ".join(differ[:3]) + (" (different mdcore version or backend?)"
                                                   if differ else "")
