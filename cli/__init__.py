"""The `sss` command-line interface (import name ``sssphase_cli``)."""
