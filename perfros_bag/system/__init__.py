"""The system model and the files that carry it.

``types``: computers, links, media, nodes with settings or curves, edges (the paper's
section II). ``systemfile``: system.yaml (and the system part of model.json), checked field
by field. ``plan``: a solver's answer and plan.json.
"""
