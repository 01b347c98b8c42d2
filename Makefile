# Two commands on a fresh machine: `make demo` and `make test`. Both create .venv and install
# omnigen with every extra, under constraints.txt (the versions the tests ran with).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
SHARED ?= ../shared
DEMO   ?= demo

.PHONY: demo test venv system clean bench

venv: $(STAMP)

# System libraries, installed when this machine lets us (root and apt): Mesa's EGL for the raster
# backend's headless rendering, and Chromium for the report's browser test. Tests that need them
# skip with the reason when they are missing.
SYSTEM_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri chromium

system:
	@missing=""; for p in $(SYSTEM_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing$$missing"; (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null) \
	      || echo "could not install$$missing: tests that need them will skip"; \
	  else echo "missing$$missing (not root or no apt): tests that need them will skip"; fi; fi

$(STAMP): pyproject.toml constraints.txt
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e ".[all,test]"
	@touch $(STAMP)

# The main job on its embedded default: convert the real KITTI sample frames when ../shared is
# beside the checkout, else a small KITTI-format tree the project generates; then validate the
# result and export it to COCO. Grows with the project (render, merge, stats).
demo: $(STAMP) system
	@set -e; \
	if [ -d "$(SHARED)/realdata/kitti/training" ]; then src="$(SHARED)/realdata/kitti"; \
	else echo "$(SHARED)/realdata not found: generating a KITTI-format sample"; \
	     $(BIN)/python -m converters.kitti_fixture "$(DEMO)/kitti-source" --frames 8; src="$(DEMO)/kitti-source"; fi; \
	$(BIN)/omnigen convert kitti "$$src" --out "$(DEMO)/kitti"; \
	$(BIN)/omnigen validate "$(DEMO)/kitti"; \
	$(BIN)/omnigen export coco "$(DEMO)/kitti" --out "$(DEMO)/kitti-coco.json"; \
	echo "demo: dataset in $(DEMO)/kitti, COCO keypoints in $(DEMO)/kitti-coco.json"

test: $(STAMP) system
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_load.py

clean:
	rm -rf $(VENV) $(DEMO) .pytest_cache
