"""A lab's archive of recordings: the single commands (fit, diagnose, online) run over many recordings.

The stage after identification: :mod:`sources` finds the recordings and keys them by content,
:mod:`tasks` runs one command on one recording (the same library call the single command makes),
:mod:`engine` spreads the tasks over a Dask cluster (a local one by default), :mod:`results` keeps
one row per task in a table that survives an interrupt and lets a rerun skip what is done, and
:mod:`example` writes a simulated archive to try it on. Docs: docs/archive.md, docs/decisions/0091.
"""
