"""Message boxes of the app as HTML: coloured like Bootstrap's alerts, the colour in the
HTML, so a new kind changes no CSS class and no layout."""

from __future__ import annotations

import html

from .glossary import in_app_words

#: Colours (text, background, border) of a message box, as Bootstrap's alerts.
ALERT_COLORS = {"info": ("#055160", "#cff4fc", "#b6effb"),
                "success": ("#0f5132", "#d1e7dd", "#badbcc"),
                "warning": ("#664d03", "#fff3cd", "#ffecb5"),
                "danger": ("#842029", "#f8d7da", "#f5c2c7")}


def alert_box(inner_html: str, kind: str) -> str:
    """``inner_html`` (escaped by the caller) in a message box of ``kind`` (a key of
    :data:`ALERT_COLORS`), with a class ``mdcore-alert-<kind>``. The colour is in the HTML,
    so a new kind changes no CSS class and no layout."""
    if kind not in ALERT_COLORS:
        raise ValueError(f"kind must be one of {sorted(ALERT_COLORS)}; received {kind!r}.")
    color, background, border = ALERT_COLORS[kind]
    return (f'<div class="mdcore-alert-{kind}" style="color:{color};background:{background};'
            f'border:1px solid {border};border-radius:4px;padding:12px 16px;margin:0">'
            f"{inner_html}</div>")


def warnings_html(advice: list[str]) -> str:
    """The diagnostics' warnings in a warning box (HTML, escaped), each "subject: text"
    with its subject in bold and mdcore's option names as the app's labels
    (:func:`~mdcore_app.glossary.in_app_words`); '' for none."""
    if not advice:
        return ""
    return alert_box("".join("<p style='margin:4px 0'><b>{}</b>{}{}</p>".format(
        *(html.escape(part) for part in in_app_words(w).partition(":"))) for w in advice),
        "warning")
