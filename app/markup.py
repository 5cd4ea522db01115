"""User text in the page's HTML and Markdown: shown literally, never read as markup.

Names from session files, uploaded file names, CSV headers, case files and exception
messages can hold anything (``<img src=x onerror=…>``): every place that puts them into HTML
or Markdown goes through one of these (Bokeh's titles, labels and options are plain text).
"""

from __future__ import annotations

import html
import re

#: ASCII punctuation: every character CommonMark lets a backslash make literal (emphasis,
#: links, code spans, raw HTML, entities, headings, lists, tables, $ maths).
_PUNCTUATION = re.compile(r"([!-/:-@\[-`{-~])")


def html_text(text) -> str:
    """``text`` as HTML that shows it literally; line breaks kept as ``<br>``."""
    return html.escape(str(text)).replace("\r\n", "\n").replace("\n", "<br>")


def markdown_text(text) -> str:
    """``text`` as Markdown that shows it literally, on one line.

    Every ASCII punctuation character is backslash-escaped, so nothing in ``text`` starts
    emphasis, a link, a code span, raw HTML, an entity or maths; line breaks become spaces
    (a new line could start a heading or a list).
    """
    return _PUNCTUATION.sub(r"\\\1", " ".join(str(text).split()))
