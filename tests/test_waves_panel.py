"""The waves of the History matching tab update in place (issue 17): the wave player only
switches renderers' visibility, a new wave adds renderers to the same figures, and the
implausibility map and the per-wave summaries hold the waves' own numbers."""

import numpy as np
import pytest

pytest.importorskip("panel")
import holoviews as hv  # noqa: E402
import panel as pn  # noqa: E402
from bokeh.document import Document  # noqa: E402
from bokeh.models import ColumnDataSource, GlyphRenderer, Plot  # noqa: E402

from mdcore_app.state import ExplorerState  # noqa: E402
from mdcore_app.waves_panel import MAX_POINTS, WavesPanel  # noqa: E402

hv.extension("bokeh")


def figures(root) -> dict[str, Plot]:
    return {p.title.text: p for p in root.select({"type": Plot})}


def wave_renderers(fig: Plot) -> list[GlyphRenderer]:
    items = [it for it in fig.legend[0].items if str(it.label.value).startswith("wave ")]
    return [it.renderers[0] for it in items]


@pytest.fixture(scope="module")
def beam1d():
    s = ExplorerState()                          # teaching preset: 5 waves on beam-1d
    panel = WavesPanel(state=s)
    root = pn.panel(panel).get_root(Document())
    s.next_wave()
    ids = {t: f.id for t, f in figures(root).items()}
    s.run_to_convergence()
    assert len(s.waves) >= 3
    return s, panel, root, ids


def test_new_waves_add_renderers_to_the_same_figures(beam1d):
    s, panel, root, ids = beam1d
    figs = figures(root)
    nroy = figs["NROY samples: l_cr vs E"]
    assert nroy.id == ids["NROY samples: l_cr vs E"]
    renderers = wave_renderers(nroy)
    assert len(renderers) == len(s.waves)
    for wave, r in zip(s.waves, renderers):
        x = np.asarray(r.data_source.data["x"])
        assert x.shape[0] == min(MAX_POINTS, wave.nroy.shape[0])
        assert np.all(np.isin(x, wave.nroy[:, 0]))         # a subset of the wave's NROY
    fraction = figs["NROY fraction per wave"]
    assert fraction.id == ids["NROY fraction per wave"]
    data = [s_.data for s_ in fraction.select({"type": ColumnDataSource}) if "percent" in s_.data]
    np.testing.assert_allclose(data[0]["percent"], [100 * w.nroy_fraction for w in s.waves])


def test_the_player_switches_visibility_and_the_map(beam1d):
    s, panel, root, _ids = beam1d
    before = {f.id for f in figures(root).values()}
    n = len(s.waves)
    s.selected_wave = 2
    try:
        figs = figures(root)
        assert {f.id for f in figs.values()} == before
        nroy = figs["NROY samples: l_cr vs E"]
        assert [r.visible for r in wave_renderers(nroy)] == [True, True] + [False] * (n - 2)
        stars = [r for r in nroy.renderers if getattr(r.glyph, "marker", None) == "star"]
        assert stars and len(stars[0].data_source.data["x"]) == 0   # θ_MAP: final wave only
        (title,) = [t for t in figs if t.startswith("wave 2: implausibility")]
        image = [d.data["image"][0] for d in figs[title].select({"type": ColumnDataSource})
                 if "image" in d.data][0]
        t1, t2, I = s.implausibility_maps[2]
        np.testing.assert_array_equal(image, np.minimum(I, 3 * s.threshold))
        fraction = [d.data for d in figs["NROY fraction per wave"].select(
            {"type": ColumnDataSource}) if "percent" in d.data][0]
        assert list(fraction["wave"]) == [1, 2]
    finally:
        s.selected_wave = n
    nroy = figures(root)["NROY samples: l_cr vs E"]
    assert all(r.visible for r in wave_renderers(nroy))
    stars = [r for r in nroy.renderers if getattr(r.glyph, "marker", None) == "star"]
    np.testing.assert_allclose([stars[0].data_source.data["x"][0],
                                stars[0].data_source.data["y"][0]], s.history_match.theta_map)


def test_one_parameter_is_a_histogram_per_wave():
    s = ExplorerState()
    s.case_name = "beam-2d"
    panel = WavesPanel(state=s)
    root = pn.panel(panel).get_root(Document())
    s.run_to_convergence()
    fig = figures(root)["NROY samples"]
    renderers = wave_renderers(fig)
    assert len(renderers) == len(s.waves) >= 2
    lo, hi = s.case.theta_bounds[0]
    for wave, r in zip(s.waves, renderers):
        nroy = wave.nroy if wave.nroy.shape[0] <= MAX_POINTS else None
        top = np.asarray(r.data_source.data["top"])
        assert top.sum() == min(MAX_POINTS, wave.nroy.shape[0])
        if nroy is not None:
            np.testing.assert_array_equal(top, np.histogram(nroy[:, 0], 40, (lo, hi))[0])


def test_a_new_match_rebuilds_the_figures():
    s = ExplorerState()
    panel = WavesPanel(state=s)
    s.next_wave()
    first = panel._nroy_figs[0]
    s.case_name = "shear-5"
    assert panel._layout.objects == [panel._empty]
    s.next_wave()
    assert len(panel._nroy_figs) == 3 and first not in panel._nroy_figs     # p = 3: 3 pairs
    assert panel._imp is None                                               # map: p = 2 only
