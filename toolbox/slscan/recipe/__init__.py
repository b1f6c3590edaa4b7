"""Recipes: named pipelines in TOML, mapped onto the stages' configuration dataclasses."""
