"""From the user's own launch file to recordings and a drafted system.yaml.

- :mod:`~perfros_bag.sweep.space` - ``space.yaml``: what to vary, and the runs of the design.
- :mod:`~perfros_bag.sweep.launchfile` - the launch file's ``<arg>``s, ``roslaunch --nodes``.
- :mod:`~perfros_bag.sweep.graph` - ``graph.yaml``: the ROS graph the master saw.
- :mod:`~perfros_bag.sweep.runner` - ``sweep``: one roscore + roslaunch + recorders per run.
- :mod:`~perfros_bag.sweep.draft` - ``init``: a system.yaml drafted from a sweep's folder.
- :mod:`~perfros_bag.sweep.deploy` - ``deploy``: a plan run here, computers as cgroups, validated.
"""
