"""``sss view``: the rig live in a browser (live view, live decode), the sessions under a folder, and
relighting that answers as a slider moves: a Starlette application over the same core runners as the CLI."""
