"""The legend of a rendered Bokeh figure, for tests that find glyphs by their label."""


def legend(fig) -> dict:
    """Legend label -> list of its glyph renderers."""
    out: dict = {}
    for item in fig.legend[0].items:
        label = item.label.value if hasattr(item.label, "value") else str(item.label)
        out.setdefault(label, []).extend(item.renderers)
    return out
