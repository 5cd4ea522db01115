"""Entry point of the Model Discrepancy Explorer: ``panel serve app/main.py``.

Each browser session runs this module and gets its own :class:`ExplorerState`, so two
sessions never see each other's results. Long work runs on a background thread and hands
its results back to the session's event loop.
"""

import holoviews as hv
import panel as pn

from mdcore import compiled
from mdcore_app.state import ExplorerState
from mdcore_app.views import ExplorerView

pn.extension(notifications=True, design="bootstrap")
hv.extension("bokeh")
# Load (or, on a new machine, compile) the numba kernels while the first page is drawn.
compiled.warm_up_in_background()


def create_app() -> pn.viewable.Viewable:
    """Build one session's page (state + view) for the current Bokeh document."""
    doc = pn.state.curdoc
    state = ExplorerState(background=doc is not None and doc.session_context is not None,
                          schedule=_scheduler(doc))
    return ExplorerView(state=state)


def _scheduler(doc):
    """Run callbacks on the session's event loop (with the document lock), or inline."""
    if doc is None or doc.session_context is None:
        return lambda fn: fn()
    return lambda fn: doc.add_next_tick_callback(fn)


if pn.state.served:
    create_app().servable(title="Model Discrepancy Explorer")
