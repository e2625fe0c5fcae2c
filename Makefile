# psdbake: `make demo` runs the pipeline on the bundled fixture, `make test` runs the tests.
# Both create the virtual environment they need from this repository's own files.

PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
OUT    ?= out
STAMP  := $(VENV)/.installed

.PHONY: demo test lint docs pages bench fidelity fuzz fixtures interop clean test-fast

$(STAMP): pyproject.toml tests/gltf/package-lock.json
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	npm ci --prefix tests/gltf --silent  # the Khronos glTF-Validator, for tests/test_gltf.py
	touch $(STAMP)

# The bundled character: fixtures/humanoid/ (17 joints, 13 sculpts: single joints and two
# shoulder+elbow combinations; made by fixtures/humanoid.py). Its layout imports into Blender
# as UsdSkel shows it (psdbake inspect warns about layouts that do not).
DEMO_ASSET    := fixtures/humanoid/humanoid.usda
DEMO_EXAMPLES := fixtures/humanoid/humanoid_examples.usda
DEMO_ANIM     := fixtures/humanoid/humanoid_anim.usda

demo: $(STAMP)
	@mkdir -p $(OUT)
	$(BIN)/psdbake inspect $(DEMO_ASSET)
	$(BIN)/psdbake pose $(DEMO_ASSET) --poses $(DEMO_EXAMPLES) -o $(OUT)/to_sculpt.usda
	$(BIN)/psdbake fit $(DEMO_ASSET) $(DEMO_EXAMPLES) -o $(OUT)/correctives.usda --report $(OUT)/fit_report.json
	$(BIN)/psdbake eval $(DEMO_ASSET) $(OUT)/correctives.usda --anim $(DEMO_ANIM) -o $(OUT)/weights.usda --points-cache $(OUT)/points_cache.usdc
	$(BIN)/psdbake stack $(DEMO_ASSET) $(OUT)/correctives.usda $(DEMO_ANIM) $(OUT)/weights.usda -o $(OUT)/shot.usda
	$(BIN)/psdbake export-gltf $(DEMO_ASSET) $(OUT)/correctives.usda --anim $(DEMO_ANIM) -o $(OUT)/shot.glb
	@echo
	@echo "Outputs in $(OUT)/:"
	@echo "  to_sculpt.usda     the character posed by plain skinning, one frame per example pose (sculpt these)"
	@echo "  correctives.usda   rest-space corrective BlendShapes + psd: RBF driver data"
	@echo "  fit_report.json    per-example residuals and black-box evaluations"
	@echo "  weights.usda       corrective weights over the shot"
	@echo "  points_cache.usdc  final posed points per frame (no UsdSkel needed)"
	@echo "  shot.usda          ASSET + CORRECTIVES + ANIM + WEIGHTS stacked: open it in any UsdSkel viewer or Blender"
	@echo "  shot.glb           the same shot as a skinned glTF with morph targets, for game engines"
	@echo "View: usdview $(OUT)/shot.usda   (compare: usdview $(DEMO_ASSET) with $(DEMO_ANIM))"

LINTED := psdbake tests benchmarks interop fixtures/generate.py fixtures/character.py fixtures/bad/make_bad.py

# The tests run on every core (pytest-xdist), a test file to a worker so that each file's
# shared fixtures are built once: 412 s against 666 s in one process on a 2-core machine.
test: $(STAMP)
	$(BIN)/ruff check $(LINTED)
	$(BIN)/mypy
	$(BIN)/python -m pytest -q -n auto --dist loadfile

# the tests that take under a second each (no fuzz, faults, farm or real characters): under a
# minute on 2 cores, for the edit-test loop; make test still runs everything, and CI calls it
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --dist loadfile -m "not slow"

lint: $(STAMP)
	$(BIN)/ruff check $(LINTED)
	$(BIN)/mypy

# The documentation site (mkdocs.yml, docs/) into site/: no warnings, no broken links (tests/test_docs.py
# builds it in make test too). The CLI reference is generated from click, the API from the docstrings.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --clean

# docs/benchmarks.md and docs/fidelity.md from the results records in benchmarks/results/*.json
# (each benchmark writes its own record; tests/test_docs.py checks the committed pages are current).
pages: $(STAMP)
	$(BIN)/python -m benchmarks.pages

fidelity: $(STAMP)
	$(BIN)/python -m benchmarks.fidelity
	$(BIN)/python -m benchmarks.humanoid
	$(BIN)/python -m benchmarks.shots
	$(BIN)/python -m benchmarks.pages
	@mkdir -p $(OUT)
	$(BIN)/psdbake compare fixtures/hinge/hinge.usda fixtures/hinge/hinge_examples.usda --anim fixtures/hinge/hinge_anim.usda -o $(OUT)/hinge_report
	$(BIN)/psdbake compare fixtures/arm_lbs.usda fixtures/arm_lbs_examples.usda --anim fixtures/arm_anim.usda -o $(OUT)/arm_report
	@echo "Open $(OUT)/hinge_report/index.html and $(OUT)/arm_report/index.html in a browser (offline)."

bench: $(STAMP)
	$(BIN)/python -m benchmarks.run
	$(BIN)/python -m benchmarks.jobs
	$(BIN)/python -m benchmarks.jobsfile
	$(BIN)/python -m benchmarks.conditioning
	$(BIN)/python -m benchmarks.coupled
	$(BIN)/python -m benchmarks.krylovfloor
	$(BIN)/python -m benchmarks.coupledtime
	$(BIN)/python -m benchmarks.evalspeed
	$(BIN)/python -m benchmarks.fitspeed
	$(BIN)/python -m benchmarks.sculptspeed
	$(BIN)/python -m benchmarks.manyjoints --global-joints 1200
	$(BIN)/python -m benchmarks.against
	$(BIN)/python -m benchmarks.startup
	$(BIN)/python -m benchmarks.pages

fuzz: $(STAMP)
	$(BIN)/python -m tests.fuzz --mode $${MODE:-all} $${CASES:+--cases $$CASES} --seed $${SEED:-0}

fixtures: $(STAMP)
	$(BIN)/python fixtures/generate.py

# interop: psdbake's stacks in Blender 5.0's default USD import vs UsdSkel.BakeSkinning (interop/run.py).
# bpy comes from PyPI with its own USD, so it lives in its own venv (bpy 5.0.1 needs Python 3.11).
BPY_PYTHON  ?= python3.11
BPY_VENV    := .venv-blender
BPY_STAMP   := $(BPY_VENV)/.installed

$(BPY_STAMP):
	$(BPY_PYTHON) -m venv $(BPY_VENV)
	echo '*' > $(BPY_VENV)/.gitignore
	$(BPY_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(BPY_VENV)/bin/python -m pip install --quiet 'bpy==5.0.1' numpy
	$(BPY_VENV)/bin/python -c "import bpy, numpy; print('bpy', bpy.app.version_string, 'numpy', numpy.__version__)"
	touch $(BPY_STAMP)

interop: $(STAMP) $(BPY_STAMP)
	BLENDER_PYTHON=$(BPY_VENV)/bin/python OUT=$(OUT) $(BIN)/python -m interop.run

clean:
	rm -rf $(OUT) site $(VENV) $(BPY_VENV) .pytest_cache .ruff_cache tests/gltf/node_modules
