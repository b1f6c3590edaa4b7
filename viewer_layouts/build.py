"""Rebuild the Rerun layouts (``*.rbl``) in this folder from :mod:`slscan.viewer.layouts`.

Run after changing a blueprint: ``python viewer_layouts/build.py``.
"""

from __future__ import annotations

import logging
from pathlib import Path

from slscan.viewer.layouts import save_layouts


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for path in save_layouts(Path(__file__).resolve().parent):
        logging.info("wrote %s", path)


if __name__ == "__main__":
    main()
