"""Decoding: from captured patterns to sub-pixel samples of known light planes, then to range maps.

Stages, one module each: ``masks`` (shadow, contrast, saturation), ``hybrid`` (the paper's
green lines indexed by red/blue bands), ``graycode`` (black/white stripes and their
edges), ``triangulate`` (ray-plane intersection), ``rangemap`` (meshing and PLY).
"""
