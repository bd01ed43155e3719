# The two commands a new user runs (see README):  make demo   and   make test
# Both create .venv on first use and install torch first (override TORCH for a CUDA build).
PYTHON ?= python3
TORCH ?= torch==2.13.0
VENV := .venv
STAMP := $(VENV)/.nhfd-installed

.PHONY: demo test lint clean browser gpu-check gpu-build

$(STAMP): pyproject.toml setup.py
	@test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q $(TORCH)
	$(VENV)/bin/python -m pip install -q -e ".[dev]"
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/nhfd demo --out out/demo

test: $(STAMP) browser
	$(VENV)/bin/ruff check .
	$(VENV)/bin/python -m pytest

clean:
	rm -rf $(VENV) build dist *.egg-info out

# The web view's browser test drives the system's Chromium (tests/web). Installed here when it is
# missing and this is root with apt-get (CI); otherwise that one test skips, saying why. Never
# fails `make test`.
browser:
	@if [ -x /usr/bin/chromium ] && command -v chromedriver >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		echo "installing chromium and chromium-driver for the web view's browser test"; \
		(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
			chromium chromium-driver >/dev/null) || \
		echo "could not install chromium: the browser test will skip"; \
	else echo "no chromium (install the chromium and chromium-driver packages): the browser \
test will skip"; fi

# On a GPU workstation (docs/gpu.md, "Checking a GPU workstation"): the CUDA tests with
# NHFD_REQUIRE_CUDA=1 (a test skipped for want of CUDA fails), the frame pipeline on the CPU and
# the GPU side by side at 1024 x 576 and 1920 x 1080, and the dataset bench on each; figures in
# out/bench/. Every step runs and prints its command; the target fails if any step failed.
# Uses .venv as it is (no reinstall: that would put the CPU onnxruntime back over onnxruntime-gpu).
GPU_TESTS := tests/pipeline/test_device.py tests/scene/test_gsplat_conventions.py \
	tests/models/test_fp16.py tests/models/test_amp.py tests/dataset/test_build_device.py \
	tests/models/test_torch_model.py \
	tests/models/test_train.py::test_a_cuda_run_resumes_on_the_cpu_from_the_same_step
GPU_BENCH_VIEWS ?= 50
gpu-check:
	@test -x $(VENV)/bin/nhfd || { echo "no $(VENV): run make test first (TORCH=... for a CUDA \
torch), then see docs/gpu.md"; exit 2; }
	@failed=""; step() { name=$$1; shift; echo "+ $$*"; "$$@" || failed="$$failed$${failed:+, }$$name"; }; \
	step "CUDA tests" env NHFD_REQUIRE_CUDA=1 $(VENV)/bin/python -m pytest -q -rfs $(GPU_TESTS); \
	step "bench pipeline" $(VENV)/bin/nhfd bench pipeline --device cpu,cuda \
		--frame-size-px 1024 576 --frame-size-px 1920 1080 --views $(GPU_BENCH_VIEWS) \
		--json out/bench/gpu_pipeline.json; \
	step "bench inference" $(VENV)/bin/nhfd bench pipeline --device cuda --inference auto,torch \
		--frame-size-px 1920 1080 --views $(GPU_BENCH_VIEWS) --json out/bench/gpu_inference.json; \
	step "bench holo cpu" $(VENV)/bin/nhfd bench holo --device cpu --scene models/scenes/donut.ply \
		--out out/bench/gpu_holo_cpu.json; \
	step "bench holo cuda" $(VENV)/bin/nhfd bench holo --device cuda \
		--scene models/scenes/donut.ply --out out/bench/gpu_holo_cuda.json; \
	if [ -n "$$failed" ]; then echo "gpu-check FAILED: $$failed"; exit 1; fi; \
	echo "gpu-check passed: figures in out/bench/gpu_pipeline.md (README table), \
out/bench/gpu_pipeline.json, out/bench/gpu_inference.md, out/bench/gpu_holo_cpu.json, out/bench/gpu_holo_cuda.json"

# The training figures on a GPU workstation: the default recipe from the shipped donut scene to a
# served model on CUDA. out/gpu_build/report.json holds each stage's seconds, the seconds per
# training step and the held-out PSNR against the 2D hologram; run again, it resumes.
gpu-build:
	@test -x $(VENV)/bin/nhfd || { echo "no $(VENV): run make test first, then see docs/gpu.md"; \
exit 2; }
	$(VENV)/bin/nhfd model build models/scenes/donut.ply --device cuda --out out/gpu_build
