# paper: the paper's Fig. 5 as a table. Table II instances 1-6 (fixtures/casestudy/),
# Problems 1 and 2, greedy (Algorithms 1-3), greedy+ and the exact optimum, with times.
#
#   make paper           -> $(OUT)/paper/fig5.md, fig5.json, fig5.png (and the table printed)

PAPER_TIME_LIMIT ?= 120

.PHONY: paper
paper: setup
	$(PY) pipelines/paper.py --out $(OUT)/paper --time-limit $(PAPER_TIME_LIMIT)
