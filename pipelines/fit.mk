# fit: system.yaml + the measured characterisation.csv -> model.json (fitted curves per
# configurable node, Fig 3/4 plots), then Problem 1 solved over the fitted continuum.
#
#   make $(OUT)/demo/model.json          fit (plots in $(OUT)/demo/fit-plots/)
#   make $(OUT)/demo/plan-fitted.json    the paper's greedy over every CPU unit of the fitted curves
#                                        (plan.json, from solve.mk, is greedy+ on the same model)
#
# $(OUT)/demo/characterisation.csv comes from the characterise pipeline (characterise.mk).

FIT_SYSTEM ?= fixtures/recordings/system.yaml
FIT_DIR := $(OUT)/demo

$(FIT_DIR)/model.json: $(FIT_SYSTEM) $(FIT_DIR)/characterisation.csv | setup
	$(BIN)/perfros-bag fit $(FIT_SYSTEM) $(FIT_DIR)/characterisation.csv --out $@ --plots $(FIT_DIR)/fit-plots

$(FIT_DIR)/plan-fitted.json: $(FIT_DIR)/model.json | setup
	$(BIN)/perfros-bag solve $< --problem 1 --method greedy --out $@

DEMO_OUTPUTS += $(FIT_DIR)/model.json $(FIT_DIR)/plan-fitted.json
