"""characterisation.csv + system.yaml -> model.json.

``regression``: scikit-learn fits and model selection by leave-one-out. ``build``: the
fitted curves per node, written into model.json.
"""
