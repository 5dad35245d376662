"""``python -m reblur``: the command line (see :mod:`reblur.cli`)."""

from __future__ import annotations

from .cli import run

if __name__ == "__main__":
    run()
