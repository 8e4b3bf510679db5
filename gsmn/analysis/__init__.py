"""Reading evaluations and training runs after the fact: the `gsmn attribute` and `gsmn analyze` commands.

failures (failure attribution over a whole evaluation), table1 (the paper's Table 1 beside ours), regions
(navigation against stopping), stop_threshold (an evaluation re-scored at a lower STOP threshold, offline), compare
(two checkpoints on the same environments), dagger (DAggerFM runs an iteration a row). Each reads `gsmn eval --json`
files, recordings (`--record`) or run folders, and prints markdown.
"""
