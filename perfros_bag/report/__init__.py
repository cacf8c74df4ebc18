"""Pictures and the HTML report.

``figures``: the one matplotlib set-up (Agg, PNG). Plot modules: ``characterisation_plots``,
``fit_plots``, ``plan_plots``, ``validation_plots``. ``html``: the self-contained page,
composed from the inputs' readers and those plots.
"""
