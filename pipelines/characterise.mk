# characterise: the bundled case-study recordings -> characterisation.csv (Table I, measured).
#
#   make $(OUT)/demo/characterisation.csv    characterise fixtures/recordings (manifest.yaml,
#                                            system.yaml and the .cpu.csv traces beside them)
#                                            + characterisation.png (CPU, frequency per setting)
#   make fixtures                            regenerate fixtures/recordings (deterministic)
#
# `perfros-bag characterise` exits 1 when a recording could not be read (the others are
# still written): that fails the demo, as it should on the bundled fixtures.

CHAR_DIR ?= fixtures/recordings
CHAR_INPUTS := $(CHAR_DIR)/manifest.yaml $(CHAR_DIR)/system.yaml $(wildcard $(CHAR_DIR)/*.cpu.csv $(CHAR_DIR)/*.bag $(CHAR_DIR)/*.mcap $(CHAR_DIR)/*/*)

$(OUT)/demo/characterisation.csv $(OUT)/demo/characterisation.png &: $(CHAR_INPUTS) | setup
	@mkdir -p $(OUT)/demo
	$(BIN)/perfros-bag characterise $(CHAR_DIR) --out $(OUT)/demo/characterisation.csv \
	  --plot $(OUT)/demo/characterisation.png

.PHONY: fixtures
fixtures: setup
	$(PY) fixtures/make_fixtures.py

DEMO_OUTPUTS += $(OUT)/demo/characterisation.csv $(OUT)/demo/characterisation.png
