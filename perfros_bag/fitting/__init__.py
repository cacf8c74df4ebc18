"""characterisation.csv + system.yaml -> model.json.

``regression``: scikit-learn fits and model selection by leave-one-out. ``build``: the
fitted curves per node, written into the system. ``modelfile``: the typed model.json
document, its writer and its reader (light: no numpy).
"""
