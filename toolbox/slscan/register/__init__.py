"""Registration: bring overlapping range scans into one frame (ICP, pose graph, MeshLab projects).

Modules: ``rangescan`` (the :class:`RangeScan` and its loaders), ``pairwise`` (coarse
and fine alignment of two scans), ``multiview`` (global alignment of many scans),
``meshlab`` (``.mlp`` projects of aligned scans).
"""
