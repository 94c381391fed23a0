"""``python -m sssphase_cli``: the ``sss`` command (what ``sss repro`` runs its parallel captures with)."""

from sssphase_cli.main import main

main()
