"""The paper's case study on real ROS 1 (section IV, V-C).

- :mod:`~perfros_bag.casestudy.nodes` - one generic rospy node script (run by Debian's
  ``/usr/bin/python3``) that plays any of the eight node types.
- :mod:`~perfros_bag.casestudy.profiles` - a node's rate, message size and CPU work at a
  parameter value, interpolated from the system's Table I settings, and the calibration.
- :mod:`~perfros_bag.casestudy.instances` - the paper's Table II instances, random and
  fleet instances.
- :mod:`~perfros_bag.casestudy.launcher` - deploy a plan: roscore, nodes, rosbag record,
  CPU trace, clean shutdown, on the machinery of :mod:`perfros_bag.rosrun` (processes,
  roscore, recorders, computers as cgroups) that ``sweep`` and ``deploy`` share.
"""
