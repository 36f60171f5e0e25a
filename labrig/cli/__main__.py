"""``python -m labrig.cli``: the ``labrig`` console entry point."""

from labrig.cli import main

main()
