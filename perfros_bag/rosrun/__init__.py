"""Running ROS 1 programs for a measurement: the machinery the case study and ``sweep`` share.

- :mod:`~perfros_bag.rosrun.processes` - a run's processes: own process groups, a run tag in
  their environment, stop with escalation, leftovers found and killed, SIGTERM as Ctrl-C.
- :mod:`~perfros_bag.rosrun.master` - roscore of our own on a free loopback port, XML-RPC
  calls to the master and to nodes.
- :mod:`~perfros_bag.rosrun.recorders` - ``rosbag record`` and ``perfros-bag record-cpu``.
- :mod:`~perfros_bag.rosrun.cgroups` - computers emulated as CPU-capped cgroups.
- :mod:`~perfros_bag.rosrun.network` - computers as network namespaces joined by tc-shaped
  veth links (10.213.0.0/16; not yet used by a launcher).
"""
