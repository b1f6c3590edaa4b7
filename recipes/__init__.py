"""The recipes shipped with slscan, installed as the package ``slscan.recipes``.

Only the TOML files beside this one are recipes; this file just lets setuptools (and an
editable install) map ``recipes/`` into the package. See ``slscan.recipe.runner.shipped_recipe``.
"""
