# Everything runs from the project's own virtual environment in .venv/.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

# Where `make demo` writes (re-running it reuses what is already there).
DEMO_DIR ?= out/demo

.PHONY: setup demo test test-slow extension clean-demo

setup: $(STAMP)

$(STAMP): requirements-dev.txt pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --upgrade --quiet pip
	$(VENV)/bin/pip install --quiet -r requirements-dev.txt -e .
	# lpips for its shipped LPIPS v0.1 linear weights only, without dependencies: it would pull
	# torchvision, whose PyPI build does not import beside the CPU torch pinned here.
	$(VENV)/bin/pip install --quiet --no-deps lpips==0.1.4
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m nerf_backend.demo --out $(DEMO_DIR)

# The default suite (about 10 minutes on 2 cores). Exit code 5 (no tests ran) fails.
test: $(STAMP)
	$(PY) -m pytest -m "not slow"

# Heavier runs, kept runnable: longer trainings and full-size renders.
test-slow: $(STAMP)
	$(PY) -m pytest -m slow

# The installable Blender extension (dist/nerf_from_blender-VERSION.zip).
extension:
	$(PYTHON) tools/build_extension.py --out dist

clean-demo:
	rm -rf $(DEMO_DIR)
