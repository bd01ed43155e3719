# The two commands a new user runs (see README):  make demo   and   make test
# Both create .venv on first use and install torch first (override TORCH for a CUDA build).
PYTHON ?= python3
TORCH ?= torch==2.13.0
VENV := .venv
STAMP := $(VENV)/.nhfd-installed

.PHONY: demo test lint clean browser

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
