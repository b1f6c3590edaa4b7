"""``python -m slscan``: the same command line as the ``slscan`` script."""

from slscan.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
