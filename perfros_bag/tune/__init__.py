"""The loop from a launch file to a plan that holds (``perfros-bag tune``).

- :mod:`~perfros_bag.tune.loop` - sweep (or reuse it, or start from a base
  characterisation), characterise, fit, solve, deploy and
  validate; then each deployment's recording as one more characterisation run, refit,
  re-solve, deploy again, until the run is within tolerance, the plan stops changing or the
  rounds run out.
- :mod:`~perfros_bag.tune.tunefile` - ``tune.json``: the rounds, the one reader and writer.
"""
