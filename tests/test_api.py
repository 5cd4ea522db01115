"""The public surface: every name in ``mdcore.__all__`` resolves, and the modules behind
it are private."""

import pathlib

import mdcore


def test_every_public_name_resolves_and_star_import_works():
    missing = [name for name in mdcore.__all__ if not hasattr(mdcore, name)]
    assert missing == []
    namespace: dict = {}
    exec("from mdcore import *", namespace)
    assert set(mdcore.__all__) <= set(namespace)
    assert len(mdcore.__all__) <= 60                 # a small surface, not every helper


def test_internal_modules_are_private():
    folder = pathlib.Path(mdcore.__file__).parent
    public = sorted(p.name for p in folder.glob("*.py")
                    if not p.name.startswith("_"))
    assert public == []
