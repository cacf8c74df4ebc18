"""Recordings + manifest -> characterisation.csv.

``manifest``: which setting each recording ran. ``table``: per-recording rows and their
aggregation. ``distributed``: an in-process or Dask task runner; ``cluster``: characterise
on Dask, big recordings split into chunk-range tasks.
"""
