# casestudy-real: the case study on Debian's real, unmodified C++ nodes (image_publisher,
# opencv_apps people_detect and smoothing), computers as CPU-capped cgroups and links as
# tc-shaped network namespaces. Long (~20-30 min); not part of `make test` or `make demo`.
#
#   make casestudy-real   cgroup fairness bench -> sweep (camera rate + both detectors) -> init
#                         (detectors drafted as driven) -> characterise -> fit -> solve with
#                         measured headroom (P1, P2; greedy, greedy+, exact) for 6 instances ->
#                         tune per instance (--base, --headroom auto) -> deploy + validate every
#                         distinct plan -> the final model's plan deployed afresh -> RQ3 ->
#                         RQ4 (pipelines/casestudy_rq4.py, below); ~35 min; results in
#                         $(OUT)/casestudy-real/ and docs/casestudy-real.md
#
# Needs root (cgroups, namespaces) and Debian's ROS 1 + opencv_apps (setup-debs installs them).
# Finished runs are reused: delete $(OUT)/casestudy-real (or one run folder) to measure again.
# Knobs: CASESTUDY_REAL_ARGS="--duration 15 --sweep-duration 12 --instances 1,2,3,4,5,6"

CASESTUDY_REAL_ARGS ?=

.PHONY: casestudy-real
casestudy-real: setup setup-debs
	$(PY) pipelines/casestudy_real.py --out $(OUT)/casestudy-real $(CASESTUDY_REAL_ARGS)
	$(PY) pipelines/casestudy_rq4.py --out $(OUT)/casestudy-real $(CASESTUDY_RQ4_ARGS)

# RQ4 (issue 30) on its own: the world changes under a running plan (a link drops to a third,
# a CPU hog takes half a robot's quota, the operator raises a camera's rate), `watch` and
# `watch --adapt` attached; ~12 min; reuses the sweep/fit of casestudy-real in the same out/
# (makes them when missing). Results: $(OUT)/casestudy-real/rq4/, table "RQ4" in
# docs/casestudy-real.md. Knobs: CASESTUDY_RQ4_ARGS="--instance 3 --steady 300 --scenarios link,hog,camera"
CASESTUDY_RQ4_ARGS ?=

.PHONY: casestudy-rq4
casestudy-rq4: setup setup-debs
	$(PY) pipelines/casestudy_rq4.py --out $(OUT)/casestudy-real $(CASESTUDY_RQ4_ARGS)
