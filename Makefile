# Everything runs from the project's own virtual environment in .venv/.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

# Where `make demo` writes (re-running it reuses what is already there).
DEMO_DIR ?= out/demo
# Where `make bench-suite` writes its datasets and its bench (re-running it resumes both).
SUITE_DIR ?= out/suite
BENCH_SUITE_DIR ?= out/bench_suite
SUITE_SCENES ?= $(wildcard ../shared/scenes/*.blend)

.PHONY: setup demo test test-blender test-gui test-slow bench-suite extension clean-demo

setup: $(STAMP)

$(STAMP): requirements-dev.txt pyproject.toml nerf_backend/requirements-no-deps.txt
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --upgrade --quiet pip
	$(VENV)/bin/pip install --quiet -r requirements-dev.txt -e .
	# lpips without its dependencies (the file says why).
	$(VENV)/bin/pip install --quiet --no-deps -r nerf_backend/requirements-no-deps.txt
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m nerf_backend.demo --out $(DEMO_DIR)

# The default suite (9 minutes on 2 cores of an AVX-512 Xeon at 93e0d82, about twice that on AVX2;
# docs/testing.md has the profile); pytest lists the 15 slowest
# tests at the end. Exit code 5 (no tests ran) fails. Two workers (pytest-xdist), a test file
# each at a time: most tests train small models whose steps are bound by Python's overhead on
# one core, so two at once finish in about two thirds of the time of one after the other.
test: $(STAMP)
	$(PY) -m pytest -m "not slow and not blender_matrix and not gui" -n 2 --dist loadfile --no-loadscope-reorder --durations=15

# The add-on in the other Blenders users run, CI's second step: the bpy 4.2 LTS and 4.5 LTS
# modules (Python 3.11), each in .venv-bpy/VERSION, and 5.1 and 5.2 LTS (Python 3.13, in the
# Debian trixie chroot of tests/blender_gui.py; root): each made on first use and kept.
test-blender: $(STAMP)
	$(PY) -m pytest -m blender_matrix --durations=15

# The real Blender programs with their GUI under Xvfb, Debian trixie's 4.3.2 and sid's newest
# (chroots built on first use and cached; root): every button pressed through Blender's event
# system, screenshots of each state in out/gui-screenshots/SUITE/; the extension repository
# installed from (CI's third step).
test-gui: $(STAMP)
	$(PY) -m pytest -m gui --durations=15

# Heavier runs, kept runnable: longer trainings and full-size renders.
test-slow: $(STAMP)
	$(PY) -m pytest -m slow

# The benchmark suite (not part of `make test`: about 90 minutes of training and scoring on 2 CPU
# cores, after the renders): the trap scenes, the demo and ../shared/scenes/*.blend rendered at
# 100x100 (100 train / 10 val / 50 test views, 64 samples; --allow-missing for RobotExpressive's
# missing texture), then preview, fast and auto trained 120 s each on every scene. Interrupted,
# it resumes where it stopped.
bench-suite: $(STAMP)
	$(PY) -m datasets_gen --suite $(SUITE_DIR) $(foreach scene,$(SUITE_SCENES),--suite-scene $(scene)) \
		--allow-missing --resolution 100 --train-views 100 --val-views 10 --test-views 50 --samples 64
	$(PY) -m nerf_backend bench --suite $(SUITE_DIR) --presets preview,fast,auto --budget-seconds 120 \
		--out $(BENCH_SUITE_DIR)

# The installable Blender extension (dist/nerf_from_blender-VERSION.zip) and the repository
# listing Blender installs and updates it from (dist/index.json).
extension:
	$(PYTHON) tools/build_extension.py --out dist

clean-demo:
	rm -rf $(DEMO_DIR)
