"""Where the real data that nobody on this project made lives (``../shared/data``)."""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "SLSCAN_DATA"


def shared_data_dir() -> Path | None:
    """The shared real-data folder: ``$SLSCAN_DATA``, else ``../shared/data`` beside the checkout.

    Returns None when neither exists (a user's fresh clone has no ``../shared``).
    """
    env = os.environ.get(ENV_VAR)
    if env:
        path = Path(env)
        return path if path.is_dir() else None
    path = Path(__file__).resolve().parents[3] / "shared" / "data"
    return path if path.is_dir() else None
