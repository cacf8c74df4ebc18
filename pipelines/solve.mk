# solve: the demo's plans, from the model fitted to the bundled recordings (fit.mk).
#
#   make $(OUT)/demo/plan.json           Problem 1, greedy+, over the fitted curves
#   make $(OUT)/demo/plan-p2.json        Problem 2 (server sized) for the same model
#
# SOLVE_INPUT=fixtures/casestudy/instance1.yaml solves the paper's reference curves instead.

SOLVE_INPUT ?= $(OUT)/demo/model.json
SOLVE_METHOD ?= greedy+

$(OUT)/demo/plan.json: $(SOLVE_INPUT) | setup
	@mkdir -p $(@D)
	$(BIN)/perfros-bag solve $(SOLVE_INPUT) --problem 1 --method $(SOLVE_METHOD) --out $@

$(OUT)/demo/plan-p2.json: $(SOLVE_INPUT) | setup
	@mkdir -p $(@D)
	$(BIN)/perfros-bag solve $(SOLVE_INPUT) --problem 2 --method $(SOLVE_METHOD) --out $@

DEMO_OUTPUTS += $(OUT)/demo/plan.json $(OUT)/demo/plan-p2.json
