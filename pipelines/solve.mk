# solve: the demo's plan, Problem 1 on the paper's Table II instance 1 (reference curves).
#
#   make $(OUT)/demo/plan.json           greedy+ plan of fixtures/casestudy/instance1.yaml
#   make $(OUT)/demo/plan-p2.json        Problem 2 (server sized) for the same system
#
# (Later the demo may solve a fitted model.json instead: change SOLVE_INPUT.)

SOLVE_INPUT ?= fixtures/casestudy/instance1.yaml
SOLVE_METHOD ?= greedy+

$(OUT)/demo/plan.json: $(SOLVE_INPUT) | setup
	@mkdir -p $(@D)
	$(BIN)/perfros-bag solve $(SOLVE_INPUT) --problem 1 --method $(SOLVE_METHOD) --out $@

$(OUT)/demo/plan-p2.json: $(SOLVE_INPUT) | setup
	@mkdir -p $(@D)
	$(BIN)/perfros-bag solve $(SOLVE_INPUT) --problem 2 --method $(SOLVE_METHOD) --out $@

DEMO_OUTPUTS += $(OUT)/demo/plan.json $(OUT)/demo/plan-p2.json
