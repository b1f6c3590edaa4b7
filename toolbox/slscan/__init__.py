"""slscan: structured-light 3D scanning after Rocchini et al. (Eurographics 2001)."""
__version__ = "0.1.0.dev0"

from slscan import _open3d

_open3d.install()  # `import open3d` without Dash and Plotly (see slscan._open3d)
