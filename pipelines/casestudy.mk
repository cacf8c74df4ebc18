# casestudy: the paper's case study on real ROS 1 (roscore, rospy nodes, rosbag record),
# computers emulated as CPU-capped cgroups. Long (~25 min); not part of `make test` or `make demo`.
#
#   make casestudy     characterise (13 runs) -> fit -> solve P1/P2 for instances 1-6 ->
#                      deploy + validate every greedy plan (12 runs) -> RQ3 (4 runs);
#                      results in $(OUT)/casestudy/ and the results section of docs/casestudy.md
#
# Needs Debian's ros-core python3-rospy python3-rosbag (setup-debs installs them as root)
# and root for the cgroups (without it the runs are marked uncapped).
# Knobs: CASESTUDY_ARGS="--duration 20 --char-duration 15 --instances 1,2,3,4,5,6 --units-per-core 400"

CASESTUDY_ARGS ?=

.PHONY: casestudy
casestudy: setup setup-debs
	$(PY) pipelines/casestudy.py --out $(OUT)/casestudy $(CASESTUDY_ARGS)
