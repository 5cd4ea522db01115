"""What the Discrepancy tab says above its plots (HTML): what runs, what to press, which
chosen method has no result yet."""

from __future__ import annotations

from .runs import method_order
from .state import ExplorerState

#: The line above the plots while none is shown and nothing runs (HTML).
EMPTY_HTML = ("No scenario has run for these settings yet: press <b>Run discrepancy</b> "
              "(it runs the history match first if there is none).")
#: ... and while no method is chosen under Scenarios.
NONE_CHOSEN_HTML = "Choose a method under <b>Scenarios</b> to see its bands."


def empty_html(s: ExplorerState) -> str:
    """The line above the plots while none is shown: what is running, or what to press."""
    if not s.busy:
        return EMPTY_HTML if s.scenarios else NONE_CHOSEN_HTML
    if s.task == "waves":
        return "Running history matching; then press <b>Run discrepancy</b>."
    matched = bool(s.waves) and s.waves[-1].status == "converged"
    return ("Running the discrepancy methods; their bands appear here when they finish."
            if matched else "Running history matching until it converges, then the "
                            "discrepancy methods; their bands appear here.")


def not_run_html(s: ExplorerState) -> str:
    """A line naming the chosen methods with no result for the current settings (a card
    that only ran waves showed scenarios 1 and 2 while the buttons said 1, 2 and 3)."""
    missing = [m.label for m in sorted(s.scenarios, key=method_order) if m not in s.results]
    return "" if s.busy or not missing else (
        f"<p>{' and '.join(missing)}: not run for these settings yet; press <b>Run "
        "discrepancy</b>.</p>")
