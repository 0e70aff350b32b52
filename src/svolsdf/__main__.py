"""``python -m svolsdf`` is the ``svolsdf`` command."""

from svolsdf.cli import main

main()
