"""The package as pyproject.toml builds it: every package under toolbox/, and the recipes.

pyproject.toml lists the packages instead of finding them so that ``recipes/`` can be
installed as ``slscan.recipes`` (``slscan demo`` runs ``recipes/demo.toml``) from its one
copy at the top level; this test keeps that list complete.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from slscan.recipe.runner import shipped_recipe

ROOT = Path(__file__).parents[1]
SETUPTOOLS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_package_under_toolbox_is_listed():
    found = {
        ".".join(p.parent.relative_to(ROOT / "toolbox").parts)
        for p in (ROOT / "toolbox").rglob("__init__.py")
        if ".egg-info" not in str(p)
    }
    listed = set(SETUPTOOLS["packages"])
    assert listed - {"slscan.recipes"} == found, (
        "pyproject.toml [tool.setuptools] packages must list every package under toolbox/: "
        f"missing {sorted(found - listed)}, not there {sorted(listed - found - {'slscan.recipes'})}"
    )


def test_the_recipes_ship_as_slscan_recipes():
    assert SETUPTOOLS["package-dir"] == {"": "toolbox", "slscan.recipes": "recipes"}
    assert SETUPTOOLS["package-data"]["slscan.recipes"] == ["*.toml"]
    assert (ROOT / "recipes" / "__init__.py").is_file()
    for recipe in sorted((ROOT / "recipes").glob("*.toml")):
        assert shipped_recipe(recipe.stem).read_text() == recipe.read_text()
