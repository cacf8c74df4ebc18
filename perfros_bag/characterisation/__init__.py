"""Recordings + manifest -> characterisation.csv.

``manifest``: which setting each recording ran. ``recording``: one recording's rows.
``table``: every recording's rows (here or on Dask) and Table I. ``csvfile``: the row type,
the writer and the checked reader of characterisation.csv. ``settings``: the rows per
(node, value, recording), what Table I, the fit and the plot aggregate. ``distributed``:
an in-process or Dask task runner; ``cluster``: characterise on Dask, big recordings split
into chunk-range tasks.
"""
