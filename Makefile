# Two commands on a fresh machine: `make demo` and `make test`. Both create .venv and install
# omnigen with every extra, under constraints.txt (the versions the tests ran with).
SHELL  := /bin/bash
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
SHARED ?= ../shared
DEMO   ?= demo

.PHONY: demo test venv system clean bench validate gpu-validate

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

# setuptools' editable install always warns that a folder named like the package could shadow it
# (a note for every project, not a problem of this one): the filter drops that one block of its output.
EDITABLE_NOTE := /BuildBackendWarning: Editable installation/,/wheel_obj:/d
$(STAMP): pyproject.toml constraints.txt
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	set -o pipefail; $(BIN)/python -m pip install --quiet -c constraints.txt -e ".[all,test]" 2>&1 | sed '$(EDITABLE_NOTE)'
	@touch $(STAMP)

# The main job on its embedded default: a few frames of the procedural city rendered with Cycles
# from each rig (two cities: seed 0 for ego and pole, seed 1 for the drone, so that the test split
# holds a whole rendered city and the evaluation scores rendered frames), real KITTI sample frames (from ../shared when it is beside the checkout, else a
# KITTI-format tree the project generates) and a generated DAIR-V2X-C tree, converted, merged into
# UrbanOmniView, validated, reported on, drawn and exported. DEMO_FRAMES and DEMO_SIZE scale it.
DEMO_FRAMES ?= 2
DEMO_EPOCHS ?= 2
DEMO_SIZE   ?= --width 320 --height 240
OMNIGEN := $(BIN)/omnigen
demo: $(STAMP) system
	@set -e; rm -rf "$(DEMO)"; mkdir -p "$(DEMO)"; \
	if [ -d "$(SHARED)/realdata/kitti/training" ]; then kitti="$(SHARED)/realdata/kitti"; \
	else echo "$(SHARED)/realdata not found: generating a KITTI-format sample"; \
	     $(BIN)/python -m omnigen.converters.kitti_fixture "$(DEMO)/kitti-source" --frames 8; kitti="$(DEMO)/kitti-source"; fi; \
	$(BIN)/python -c "from omnigen.converters.dair_fixture import write_dair_tree; write_dair_tree('$(DEMO)/dair-source', 12, seed=0, variant='c')"; \
	for rig_seed in ego:0 pole:0 drone:1; do rig=$${rig_seed%:*}; seed=$${rig_seed#*:}; \
	  $(OMNIGEN) render --rig $$rig --frames $(DEMO_FRAMES) --seed $$seed $(DEMO_SIZE) --quality preview --out "$(DEMO)/render-$$rig"; done; \
	$(OMNIGEN) convert kitti "$$kitti" --out "$(DEMO)/kitti"; \
	$(OMNIGEN) convert dair "$(DEMO)/dair-source" --out "$(DEMO)/dair"; \
	$(OMNIGEN) merge "$(DEMO)"/render-* "$(DEMO)/kitti" "$(DEMO)/dair" --out "$(DEMO)/uov" --test-fraction 0.25; \
	$(OMNIGEN) validate "$(DEMO)/uov"; \
	$(OMNIGEN) stats "$(DEMO)/uov" --out "$(DEMO)/report"; \
	$(OMNIGEN) show "$(DEMO)/uov" kitti-000001 --bev --out "$(DEMO)/kitti-000001.png"; \
	$(OMNIGEN) show "$(DEMO)/uov" synthetic-drone-s1-000000 --bev --out "$(DEMO)/synthetic-drone-s1-000000.png"; \
	$(OMNIGEN) export coco "$(DEMO)/uov" --out "$(DEMO)/uov-coco.json"; \
	$(OMNIGEN) export yolo "$(DEMO)/uov" --out "$(DEMO)/uov-yolo"; \
	$(OMNIGEN) train "$(DEMO)/uov" --out "$(DEMO)/run" --epochs $(DEMO_EPOCHS) --workers 0 model.imgsz=320 optim.batch=8 \
	  crop_stage.steps=30 crop_stage.batch=16; \
	$(OMNIGEN) eval "$(DEMO)/run/best.pt" "$(DEMO)/uov" --split test --imgsz 320 --out "$(DEMO)/eval.json"; \
	echo; echo "demo: UrbanOmniView in $(DEMO)/uov; open $(DEMO)/report/index.html in a browser;"; \
	echo "      frames drawn in $(DEMO)/*.png; COCO and YOLO exports beside them;"; \
	echo "      a detector smoke run in $(DEMO)/run and its evaluation in $(DEMO)/eval.json ($(DEMO_EPOCHS) epochs:"; \
	echo "      the pipeline runs end to end; a useful model needs make validate or a GPU, docs/detector-training.md)"

# One pytest worker per core (pytest-xdist), each test file on one worker so that its module
# fixtures are built once; TEST_JOBS=0 runs them in this process.
TEST_JOBS ?= auto
test: $(STAMP) system
	$(BIN)/python -m pytest -q -n $(TEST_JOBS) --dist loadfile

# Every figure quoted in the docs; each script prints its own (slow: generates large fake datasets,
# renders with Cycles on the CPU). Left out, as they need what this target cannot give them: a
# dataset (make validate's runs/validate/uov) for bench_adherence_floor.py, bench_learning.py,
# bench_crop_stage.py --dataset and bench_train_speed.py cache; two make validate results.json
# files for compare_results.py; a GPU for gpu_validate.py and peer_ultralytics.py (make
# gpu-validate); validate.py is make validate.
bench: $(STAMP)
	$(BIN)/python benchmarks/bench_load.py
	$(BIN)/python benchmarks/bench_merge_export.py
	$(BIN)/python benchmarks/bench_stats.py
	$(BIN)/python benchmarks/bench_convert_kitti.py
	$(BIN)/python benchmarks/bench_convert_dair.py
	$(BIN)/python benchmarks/bench_image_check.py --repeats 30
	$(BIN)/python benchmarks/bench_scene.py
	$(BIN)/python benchmarks/bench_render.py
	$(BIN)/python benchmarks/bench_render_scale.py
	$(BIN)/python benchmarks/bench_realism.py --cycles-frames 0
	$(BIN)/python benchmarks/bench_realism.py --frames 4 --size 320 --cycles-frames 4 --cycles-size 320
	$(BIN)/python benchmarks/bench_detector_size.py
	$(BIN)/python benchmarks/bench_detector_latency.py
	$(BIN)/python benchmarks/bench_train_speed.py step --overfit
	$(BIN)/python benchmarks/bench_train_speed.py step --loop --steps 21
	$(BIN)/python benchmarks/bench_train_speed.py throughput --device cpu --imgsz 320 --batch 8 --steps 12 --workers 1
	$(BIN)/python benchmarks/bench_eval.py
	$(BIN)/python benchmarks/bench_eval_kitti.py
	$(BIN)/python benchmarks/bench_bev.py

# End to end on a 2-core machine (training time-boxed to 125 minutes; RESULTS.md lists every stage): render all three rigs, merge with the real KITTI
# sample frames, train nano+P2, evaluate, run the BEV head; writes docs/RESULTS.md and
# docs/results.json. Resumable; VALIDATE_ARGS scales it (benchmarks/validate.py): '--ablations
# no-synthetic' adds minutes (3 KITTI frames); no-p2 and hires each train about as long as the main run.
VALIDATE_ARGS ?=
validate: $(STAMP) system
	$(BIN)/python benchmarks/validate.py $$( [ -d "$(SHARED)/realdata/kitti/training" ] && echo --kitti "$(SHARED)/realdata/kitti" ) $(VALIDATE_ARGS)

# On one GPU machine with the machine's own Python (docs/gpu.md): render, train for 7 minutes, evaluate,
# within 12 minutes; GPU_ARGS='--wheels DIR' installs what is missing from fetch_gpu_wheels.py's folder.
GPU_PYTHON ?= python3
GPU_WORK   ?= runs/gpu-validate
GPU_ARGS   ?=
gpu-validate:
	$(GPU_PYTHON) benchmarks/gpu_validate.py --work $(GPU_WORK) $(GPU_ARGS)

clean:
	rm -rf $(VENV) $(DEMO) .pytest_cache
