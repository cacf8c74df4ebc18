# validate, export, report: the end of the pipeline (eq 10), on the demo plan.
#
# The demo has no robot to deploy to: pipelines/simulate_run.py writes a run recording
# ($(OUT)/demo/run.mcap, every planned topic at its planned rate) and its CPU trace
# (run.cpu.csv) from the plan; `validate` then checks it against the plan, `export` writes
# the launch files and `report` one HTML page with whatever the other demo steps made.
#
#   make $(OUT)/demo/validation.json     validate the simulated run (exit 1 fails the demo)
#   make $(OUT)/demo/report/index.html   the report
#   make report-check                    render the report in headless chromium, no console errors

DEMO_DIR := $(OUT)/demo
DEMO_PLAN := $(DEMO_DIR)/plan.json
# Optional report inputs, when an earlier pipeline (included before this one) makes them.
DEMO_REPORT_CHAR := $(filter $(DEMO_DIR)/characterisation.csv,$(DEMO_OUTPUTS))
DEMO_REPORT_MODEL := $(filter $(DEMO_DIR)/model.json,$(DEMO_OUTPUTS))

$(DEMO_DIR)/run.mcap: $(DEMO_PLAN) pipelines/simulate_run.py | setup
	$(PY) pipelines/simulate_run.py $(DEMO_PLAN) $@ --seconds 20

$(DEMO_DIR)/validation.json: $(DEMO_DIR)/run.mcap $(DEMO_PLAN) | setup
	$(BIN)/perfros-bag validate $(DEMO_DIR)/run.mcap $(DEMO_PLAN) --out $@

$(DEMO_DIR)/system.launch: $(DEMO_PLAN) | setup
	$(BIN)/perfros-bag export $(DEMO_PLAN) --format roslaunch --out $@

$(DEMO_DIR)/params.yaml: $(DEMO_PLAN) | setup
	$(BIN)/perfros-bag export $(DEMO_PLAN) --format ros2-params --out $@

$(DEMO_DIR)/report/index.html: $(DEMO_PLAN) $(DEMO_DIR)/validation.json $(DEMO_REPORT_CHAR) $(DEMO_REPORT_MODEL) | setup
	$(BIN)/perfros-bag report --plan $(DEMO_PLAN) --validation $(DEMO_DIR)/validation.json \
	  $(if $(DEMO_REPORT_CHAR),--characterisation $(DEMO_REPORT_CHAR)) \
	  $(if $(DEMO_REPORT_MODEL),--model $(DEMO_REPORT_MODEL)) --out $(DEMO_DIR)/report

DEMO_OUTPUTS += $(DEMO_DIR)/validation.json $(DEMO_DIR)/system.launch $(DEMO_DIR)/params.yaml \
	$(DEMO_DIR)/report/index.html

.PHONY: report-check
# Opens the demo report in headless chromium: the plan table must be in the DOM and the
# browser log must have no console error.
report-check: $(DEMO_DIR)/report/index.html setup-debs
	@tmp=$$(mktemp -d); \
	chromium --headless --no-sandbox --disable-gpu --disable-background-networking \
	  --disable-component-update --disable-sync --no-first-run --user-data-dir=$$tmp/profile \
	  --enable-logging=stderr --v=0 --dump-dom "file://$(abspath $<)" >$$tmp/dom.html 2>$$tmp/log.txt; \
	rc=$$?; \
	if [ $$rc -ne 0 ]; then echo "report-check: chromium failed ($$rc)"; cat $$tmp/log.txt; exit 1; fi; \
	if ! grep -q 'id="plan-table"' $$tmp/dom.html; then echo "report-check: no plan table in the page"; exit 1; fi; \
	if grep -E 'Uncaught|ERROR:CONSOLE' $$tmp/log.txt; then echo "report-check: console errors"; exit 1; fi; \
	rm -rf $$tmp; echo "report-check: $< renders, plan table present, no console errors"
