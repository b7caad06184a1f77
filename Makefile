# KneeMesh: two commands on a fresh machine.
#   make demo   set up .venv if needed and run the main job on the bundled sample knee
#   make test   set up .venv with the test and training extras and run the whole test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo-output
# One text encoding whatever the locale (CI runs with an ASCII one).
export PYTHONUTF8 = 1

.PHONY: demo test bench clean venv

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# Reinstall only when the dependency list changes: a second run is fast.
$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install --quiet --disable-pip-version-check -e ".[test,train]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/kneemesh inspect kneemesh/data/right_knee_example.nrrd
	$(VENV)/bin/kneemesh mesh kneemesh/data/right_knee_example.nrrd --out $(DEMO_OUT)
	@echo "Outputs are in $(abspath $(DEMO_OUT)) (meshes/, report.json)."

test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadgroup -q

bench: $(STAMP)
	$(PY) -m pip install --quiet -e ".[test,bench]"
	$(PY) bench/bones.py

clean:
	rm -rf $(DEMO_OUT) .pytest_cache
