"""The app's in-place figures refuse bad arrays with a ValueError naming the argument, and
keep what they showed."""

import numpy as np
import pytest

pytest.importorskip("bokeh")
from bokeh.document import Document  # noqa: E402
from bokeh.models import ColumnDataSource  # noqa: E402

from mdcore_app.live_figures import BandFigure, MapFigure  # noqa: E402
from mdcore_app.sources import blank, replace_data, set_range, set_top  # noqa: E402

X = np.linspace(0.0, 1.0, 5)
GOOD = {"x": X, "mean": X ** 2, "var": np.full(5, 0.01), "k": 2}


def band():
    fig = BandFigure(title="t", xname="x", yname="y", color="red", label="S1",
                     reference="true δ")
    fig.show(**GOOD, reference=X)
    return fig


def test_a_good_band_is_mean_plus_minus_k_sd():
    fig = band()
    np.testing.assert_allclose(fig._band.data["upper"] - fig._band.data["lower"],
                               2 * 2 * 0.1 * np.ones(5))


@pytest.mark.parametrize("change, name", [
    ({"mean": np.r_[X[:4], np.nan]}, "mean"),
    ({"var": np.full(4, 0.01)}, "var"),
    ({"var": np.r_[np.full(4, 0.01), -1e-3]}, "var"),
    ({"x": np.array([]), "mean": np.array([]), "var": np.array([])}, "x"),
    ({"x": X[:, None]}, "x"),
    ({"k": 0}, "k"),
    ({"reference": X[:3]}, "reference"),
    ({"reference": np.r_[X[:4], np.inf]}, "reference"),
])
def test_bad_band_arrays_are_refused_and_the_plot_kept(change, name):
    fig = band()
    before = {k: np.array(v) for k, v in fig._band.data.items()}
    kwargs = {**GOOD, "reference": X, **change}
    with pytest.raises(ValueError, match=name):
        fig.show(**kwargs)
    for k, v in before.items():
        np.testing.assert_array_equal(fig._band.data[k], v)


@pytest.mark.parametrize("values, name", [
    (np.full((3, 4), np.nan), "values"),
    (np.zeros((4, 3)), "values"),
    (np.zeros(12), "values"),
    (np.zeros((0, 4)), "values"),
])
def test_bad_maps_are_refused(values, name):
    fig = MapFigure(title="t", xname="x1", yname="x2", zname="z", u1=np.arange(4.0),
                    u2=np.arange(3.0), diverging=True)
    fig.show(np.arange(12.0).reshape(3, 4))
    with pytest.raises(ValueError, match=name):
        fig.show(values)
    np.testing.assert_array_equal(fig._image.data["image"][0], np.arange(12.0).reshape(3, 4))
    assert (fig._mapper.low, fig._mapper.high) == (-11.0, 11.0)     # symmetric about 0
    assert fig.figure.xaxis[0].ticker.desired_num_ticks == 4      # legible at 1280 px


def test_show_pane_and_show_only_show_a_pane_again_and_refuse_bad_arguments():
    import panel as pn
    from bokeh.plotting import figure

    from mdcore_app.live_figures import LivePanel, figure_pane, show_only, show_pane

    panes = {o: figure_pane(figure()) for o in range(3)}
    parent = pn.Row()
    show_only(panes, 1, parent, attach=True)
    assert parent.objects == list(panes.values())
    assert [p.visible for p in panes.values()] == [False, True, False]
    show_only(panes, 0, parent, attach=False)          # hidden, then shown again
    assert panes[0].visible and panes[0].object.visible and not panes[1].visible
    for bad, match in [((object(), True), "pane must be a Panel object"),
                       ((panes[0], "yes"), "shown must be True or False"),
                       ((panes[0], None), "shown must be True or False")]:
        with pytest.raises(ValueError, match=match):
            show_pane(*bad)
    with pytest.raises(ValueError, match=r"shown must be a key of panes, one of \[0, 1, 2\]"):
        show_only(panes, 7, parent, attach=False)
    assert panes[0].visible                            # nothing changed
    for bad in [(), (pn.Tabs(), -1), (object(), 1), ("tabs", -1)]:
        with pytest.raises(ValueError, match=r"shown_in must be \(tabs, index\)"):
            LivePanel(shown_in=bad)


def _events(source):
    """Attach ``source`` to a document; return the list its change events are appended to."""
    doc, sent = Document(), []
    doc.add_root(source)
    doc.on_change(lambda event: sent.append(type(event).__name__))
    return sent


def test_same_shape_data_go_as_a_patch_of_the_changed_columns_only():
    """A patch leaves the browser's legends alone (a new ``data`` dict rebuilt each legend
    entry, with a new canvas, several times per update), and unchanged columns are not
    sent."""
    source = ColumnDataSource(blank(5, "y", x=X))
    assert np.isnan(source.data["y"]).all()
    sent = _events(source)
    mine = X ** 2                                         # e.g. a cached result's array
    replace_data(source, {"x": X, "y": mine})
    assert sent == ["ColumnsPatchedEvent"]
    np.testing.assert_array_equal(source.data["y"], mine)
    replace_data(source, {"x": X, "y": mine})            # nothing changed: nothing sent
    assert sent == ["ColumnsPatchedEvent"]
    replace_data(source, {"x": X, "y": 2 * mine})
    assert sent == ["ColumnsPatchedEvent"] * 2
    np.testing.assert_array_equal(mine, X ** 2)          # the caller's array is untouched


def test_new_lengths_or_columns_replace_the_data_with_copies():
    source = ColumnDataSource({"x": [], "y": []})
    sent = _events(source)
    mine = X ** 2
    replace_data(source, {"x": X, "y": mine})             # a new length: new data
    assert sent == ["ColumnDataChangedEvent"]
    assert source.data["y"] is not mine
    replace_data(source, {"x": X, "y": 3 * X})           # now patched, into the copy
    assert sent[-1] == "ColumnsPatchedEvent"
    np.testing.assert_array_equal(mine, X ** 2)
    replace_data(source, {"x": X, "y": X.astype(int)})   # another dtype: new data
    replace_data(source, {"x": X[:3], "y": X[:3]})       # shorter: new data
    replace_data(source, {"x": [0.0, 1.0], "y": [1.0, 2.0]})   # lists: new data
    assert sent[-3:] == ["ColumnDataChangedEvent"] * 3
    assert list(source.data["y"]) == [1.0, 2.0]


def test_blank_rows_compare_equal_so_an_unchanged_padded_column_is_not_resent():
    source = ColumnDataSource(blank(4, "y", x=np.arange(4.0)))
    sent = _events(source)
    replace_data(source, {"x": np.arange(4.0), "y": np.array([1.0, np.nan, np.nan, np.nan])})
    replace_data(source, {"x": np.arange(4.0), "y": np.array([1.0, np.nan, np.nan, np.nan])})
    assert sent == ["ColumnsPatchedEvent"]


@pytest.mark.parametrize("x", [[0.0, np.nan, 1.0], np.zeros((3, 2)), np.array([])])
def test_band_figure_refuses_bad_inputs_to_start_at(x):
    with pytest.raises(ValueError, match="x"):
        BandFigure(title="t", xname="x", yname="y", color="red", label="S1", x=x)


def test_set_range_sends_only_a_change_and_set_top_pads_the_top():
    from bokeh.document import Document
    from bokeh.models import Range1d

    r = Range1d(0.0, 1.0)
    doc = Document()
    doc.add_root(r)
    seen = []
    doc.on_change(lambda e: seen.append(e))
    set_range(r, 0.0, 1.0)
    assert seen == []                                   # the same bounds: nothing sent
    set_top(r, 40.0, pad=0.08)
    assert (r.start, r.end) == (0.0, pytest.approx(43.2)) and len(seen) >= 1
    set_top(r, 0.0)                                     # nothing to show yet
    assert (r.start, r.end) == (0.0, 1.0)
