"""The system model and the files that carry it.

``types``: computers, links, media, nodes with settings or curves, edges (the paper's
section II), and the model's rules on a placement (capacities, routes, link loads).
``systemfile``: system.yaml (and the system part of model.json), checked field by field.
``plan``: a solver's answer and the plan types (problem, method, status as enums);
``rules``: an answer made into a plan (loads, objective, topic expectations);
``planfile``: plan.json, read and written.
"""
