# Set-up is part of every target: a venv in .venv, the project with its test extra, and Debian's EGL/Mesa.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
EGL_PACKAGES := libegl1 libgl1-mesa-dri libegl-mesa0
BROWSER_PACKAGES := chromium
STAMP := $(VENV)/.installed
VIEWER := server/viewer
NPM_STAMP := $(VIEWER)/node_modules/.package-lock.json

.PHONY: setup demo test bench fuzz clean system-deps browser-deps

setup: $(STAMP) $(NPM_STAMP) system-deps

# The viewer page's JavaScript dependency (fzstd), exactly as locked.
$(NPM_STAMP): $(VIEWER)/package.json $(VIEWER)/package-lock.json
	cd $(VIEWER) && npm ci --no-audit --no-fund --loglevel=error

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test,scenes]'
	touch $(STAMP)

# Mesa's EGL (llvmpipe) for headless GL: apt-get when root, otherwise say what to install.
system-deps:
	@if ! ldconfig -p | grep -q libEGL_mesa; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    echo "installing $(EGL_PACKAGES)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(EGL_PACKAGES) >/dev/null; \
	  else \
	    echo "error: headless GL needs Debian packages $(EGL_PACKAGES); run: sudo apt-get install $(EGL_PACKAGES)"; \
	    exit 1; \
	  fi; \
	fi

# Debian's Chromium for the browser tests and `quadcast bench browser` (playwright drives /usr/bin/chromium):
# apt-get when root; otherwise the browser tests skip, saying why.
browser-deps:
	@if [ ! -x /usr/bin/chromium ]; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    echo "installing $(BROWSER_PACKAGES)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(BROWSER_PACKAGES) >/dev/null; \
	  else \
	    echo "note: the browser tests need Debian's $(BROWSER_PACKAGES); run: sudo apt-get install $(BROWSER_PACKAGES)"; \
	  fi; \
	fi

demo: setup
	$(BIN)/quadcast demo

# The tests, and the import-linter contract in pyproject.toml (a layer that imports one above it fails).
test: setup browser-deps
	$(BIN)/lint-imports
	$(BIN)/python -m pytest

# 100,000 hypothesis inputs per decoder and through the server's pose path: unexpected exceptions, hangs, peak RSS
# (exit 1 on any unexpected exception or hang). `make test` runs a short version (tests/test_fuzz.py).
fuzz: setup
	$(BIN)/python -m quadcast.sim.fuzz --examples 100000

# Speed and size figures (not tests): renderer, server pipeline, client stages, YORO stereo.
bench: setup
	$(BIN)/quadcast bench render
	$(BIN)/quadcast bench server
	$(BIN)/quadcast bench client
	$(BIN)/quadcast bench stereo --sizes 960x540
	$(MAKE) browser-deps
	$(BIN)/quadcast bench browser --sizes 960x540

clean:
	rm -rf $(VENV) out .pytest_cache .hypothesis $(VIEWER)/node_modules
