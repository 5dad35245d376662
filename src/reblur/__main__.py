"""``python -m reblur``: the command line (see :mod:`reblur.cli`)."""

from __future__ import annotations

from .cli import main

if __name__ == "__main__":
    main(prog_name="reblur")
