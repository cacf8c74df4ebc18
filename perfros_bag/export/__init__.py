"""plan.json -> a ROS 1 launch file or ROS 2 parameters."""
