"""``watch``: a running plan checked live against its model's prediction, window by window,
and re-planned (``--adapt``) when a drift persists.

- :mod:`~perfros_bag.watch.counters`: what ROS 1 already counts (the publishers'
  ``getBusStats``), read as per-topic message and byte counters, and their differences;
- :mod:`~perfros_bag.watch.observe`: the live system read without perturbing it (master and
  node XML-RPC, psutil CPU time by the PID each node's ``getPid`` gives);
- :mod:`~perfros_bag.watch.window`: one window as statistics that validation's eq 10
  (:func:`perfros_bag.validation.eq10.check_run`) takes, and its JSON object;
- :mod:`~perfros_bag.watch.stamps`: a predicted chain's latency from its last topic's header
  stamps (a TCPROS subscriber of its own, to that small topic only);
- :mod:`~perfros_bag.watch.alarms`: drifts that persist for N windows become alarms;
- :mod:`~perfros_bag.watch.adapt`: refit with the live windows, re-solve, write the new plan;
- :mod:`~perfros_bag.watch.loop`: the loop, attached to ``ROS_MASTER_URI`` or a deploy;
- :mod:`~perfros_bag.watch.watchfile`: a ``watch --out`` folder read back (for the report).
"""
