"""The README's Glossary and the app's tooltips are one text (app/glossary.py), every word
issue 41 names is defined, and nothing cites a SPEC that a clone does not have."""

import re
from pathlib import Path

from mdcore_app.glossary import GLOSSARY, SECTION, tooltip

ROOT = Path(__file__).resolve().parent.parent
NAMED = ("NROY", "V_o", "V_m", "T", "θ_MAP", "LPL", "MMD", "NMSE", "k̂", "IAT", "ESS over φ",
         "scenario 1", "scenario 2", "scenario 3", "KOH")


def readme_glossary() -> dict:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text[text.index("## Glossary"):]
    section = section[:section.index("\n## ", 1)]
    rows = re.findall(r"^\| (.+?) \| (.+?) \| \[§(\d)\]\(docs/method\.md\) \|$", section, re.M)
    assert len(rows) == section.count("\n| ") - 1               # every row but the header
    return {term: (meaning, int(n)) for term, meaning, n in rows}


def test_the_readme_glossary_is_the_tooltips_text():
    readme = readme_glossary()
    assert set(NAMED) <= set(readme)
    assert readme == {t: (GLOSSARY[t], SECTION[t]) for t in readme}   # every README term is in
    assert set(GLOSSARY) == set(SECTION) == set(readme)


def test_each_definition_points_to_a_section_that_exists():
    method = (ROOT / "docs" / "method.md").read_text(encoding="utf-8")
    for term in GLOSSARY:
        assert f"\n## {SECTION[term]}. " in method, term
        assert tooltip(term).endswith(f"(docs/method.md §{SECTION[term]})")
        assert "|" not in GLOSSARY[term]                          # a table cell stays one cell
    assert "star" in GLOSSARY["θ_MAP"] and "×" in GLOSSARY["θ_MAP"]


def test_no_doc_cites_the_spec():
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = path.read_text(encoding="utf-8")
        assert "SPEC §" not in text and "shared/SPEC.md" not in text, path.name


#: Every word of issue 41's list that the app shows, as the glossary spells it.
ON_SCREEN = (*NAMED, "RMSE δ", "ESS", "N_s, N_φ")


def test_every_word_on_screen_has_its_glossary_tooltip_and_no_spec():
    """Tooltips of the controls (their description or help icon) and the tabs' word lines
    hold each word's glossary text; nothing on screen cites SPEC."""
    import html

    import panel as pn

    from mdcore_app.state import ExplorerState
    from mdcore_app.views import ExplorerView

    page = ExplorerView(state=ExplorerState()).__panel__()
    texts = [str(p.object) for p in page.select(pn.pane.PaneBase)]
    texts += [str(w.value) for w in page.select(pn.widgets.TooltipIcon)]
    texts += [str(getattr(w, "description", "") or "") for w in page.select(pn.widgets.Widget)]
    shown = html.unescape(" ".join(texts))
    for term in ON_SCREEN:
        assert tooltip(term) in shown, term
    assert "SPEC" not in shown


def test_messages_name_the_apps_controls_not_mdcores_options():
    """The diagnostics' advice said "Add simulator runs (n_runs)" beside a field called
    "Runs per wave"; messages now use the controls' labels (other words stay)."""
    from mdcore_app.alerts import warnings_html
    from mdcore_app.glossary import in_app_words

    advice = ("wave 2: 3 of its 12 runs would be ruled out. Add simulator runs (n_runs), "
              "raise V_m if the simulator itself is near the cut-off.")
    shown = warnings_html([advice])
    assert "Add simulator runs (“Runs per wave”), raise V_m" in shown and "n_runs" not in shown
    assert in_app_words("raise n_phi or n_s (n_starts and n_samples stay)") == \
        "raise “N_φ” or “N_s” (n_starts and n_samples stay)"
