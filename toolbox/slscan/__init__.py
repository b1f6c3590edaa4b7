"""slscan: structured-light 3D scanning after Rocchini et al. (Eurographics 2001)."""
__version__ = "0.1.0.dev0"
