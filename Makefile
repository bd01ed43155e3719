# The two commands a new user runs (see README):  make demo   and   make test
# Both create .venv on first use and install torch first (override TORCH for a CUDA build).
PYTHON ?= python3
TORCH ?= torch==2.13.0
VENV := .venv
STAMP := $(VENV)/.nhfd-installed
# The suite in two runs: the tests that do not time a control loop on two pytest-xdist workers,
# a file each (PYTEST_WORKERS= runs them in one process), then those that do (marked solo:
# heartbeat gaps, a daemon thread beside a CPU burner) in one process with the machine to
# themselves. OpenMP's threads sleep when idle instead of spinning (OMP_WAIT_POLICY=PASSIVE, as
# the frame worker's do): two workers' spinning pools on two cores took the cores from each
# other and from the daemons the tests start (the parallel run: 600 s spinning, 484 s not).
PYTEST_WORKERS ?= -n 2 --dist loadfile

.PHONY: demo test lint clean browser gpu-check gpu-prepare gpu-build

$(STAMP): pyproject.toml setup.py
	@test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q $(TORCH)
	$(VENV)/bin/python -m pip install -q -e ".[dev]"
	$(VENV)/bin/nhfd warmup
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/nhfd demo --out out/demo

test: $(STAMP) browser
	$(VENV)/bin/ruff check .
	OMP_WAIT_POLICY=PASSIVE $(VENV)/bin/python -m pytest -m "not solo" $(PYTEST_WORKERS); \
	rest=$$?; \
	$(VENV)/bin/python -m pytest -m solo; solo=$$?; test $$rest = 0 && test $$solo = 0

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

# On a GPU machine (docs/gpu.md, "Checking a GPU"): scripts/gpu_check.sh runs the CUDA tests with
# NHFD_REQUIRE_CUDA=1 (a test skipped for want of CUDA fails), then the GPU figures beside the
# CPU's (bench holo, a short GPU training run, bench pipeline at 1024 x 576 and 1920 x 1080, one
# profiled frame, the network's precision and layout variants); every step runs under its own
# limit, its log and figures packed into out/gpu/. Uses .venv as it is (no reinstall: that would
# put the CPU onnxruntime back over onnxruntime-gpu). A lent GPU machine without nhfd runs the
# script itself after `make gpu-prepare` here (docs/gpu.md).
GPU_STEPS ?= env,gsplat,tests,holo,train,pipeline,frame,net
GPU_DEADLINE_S ?= 3600
gpu-check:
	@test -x $(VENV)/bin/nhfd || { echo "no $(VENV): run make test first (TORCH=... for a CUDA \
torch), then see docs/gpu.md"; exit 2; }
	PYTHON=$(VENV)/bin/python GPU_STEPS=$(GPU_STEPS) GPU_DEADLINE_S=$(GPU_DEADLINE_S) \
		OUT=out/gpu GPU_WORK=out/gpu/work bash scripts/gpu_check.sh

# What a bare GPU machine lacks, prepared on this one: the wheels (.whl/), gsplat's CUDA
# extension built ahead for sm_90 and the shared scenes (.gpu/). See scripts/gpu_prepare.sh.
gpu-prepare:
	bash scripts/gpu_prepare.sh

# The training figures on a GPU workstation: the default recipe from the shipped donut scene to a
# served model on CUDA. out/gpu_build/report.json holds each stage's seconds, the seconds per
# training step and the held-out PSNR against the 2D hologram; run again, it resumes.
gpu-build:
	@test -x $(VENV)/bin/nhfd || { echo "no $(VENV): run make test first, then see docs/gpu.md"; \
exit 2; }
	$(VENV)/bin/nhfd model build models/scenes/donut.ply --device cuda --out out/gpu_build
