# KneeMesh: two commands on a fresh machine.
#   make demo   set up .venv (the runtime only) and CalculiX if needed and run the main job on the bundled sample knee
#   make test   set up .venv with the test and training extras, CalculiX and a headless Chromium, and run the whole test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
RUNTIME := $(VENV)/.runtime
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo-output
# One text encoding whatever the locale (CI runs with an ASCII one).
export PYTHONUTF8 = 1

.PHONY: demo test bench clean venv ccx browser

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# Reinstall only when the dependency list changes: a second run is fast.  The demo needs the runtime
# alone; the tests add their tools and the training extra (PyTorch) on top.
$(RUNTIME): pyproject.toml | $(PY)
	$(PY) -m pip install --quiet --disable-pip-version-check -e .
	touch $(RUNTIME)

$(STAMP): pyproject.toml $(RUNTIME)
	$(PY) -m pip install --quiet --disable-pip-version-check -e ".[test,train]"
	touch $(STAMP)

venv: $(STAMP)

# CalculiX proves the decks: installed from the distribution where it is missing (as root), else
# the command to run is printed and make stops.
ccx:
	@command -v ccx >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq calculix-ccx >/dev/null; \
	  else echo "CalculiX is missing: run  sudo apt-get install calculix-ccx  (Debian/Ubuntu), then make again." >&2; exit 1; fi; }
	@ccx -v 2>/dev/null | grep -m1 Version || true

# A real browser opens the cohort report in the tests: Chromium's headless shell, the same way.
browser:
	@command -v chromium-headless-shell >/dev/null 2>&1 || command -v chromium >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium-headless-shell >/dev/null; \
	  else echo "Chromium is missing: run  sudo apt-get install chromium-headless-shell  (Debian/Ubuntu), then make again." >&2; exit 1; fi; }

demo: $(RUNTIME) ccx
	$(VENV)/bin/kneemesh inspect kneemesh/data/right_knee_example.nrrd
	$(VENV)/bin/kneemesh mesh kneemesh/data/right_knee_example.nrrd --out $(DEMO_OUT) --simulate smoke
	@echo "Outputs are in $(abspath $(DEMO_OUT)): meshes/, attachments.json/.png, fe/ (decks; smoke/ results.json, contact.png, pressure_*.vtu), report.json."

test: $(STAMP) ccx browser
	$(PY) -m pytest -n 2 --dist loadgroup -q --durations=12

bench: $(STAMP)
	$(PY) -m pip install --quiet -e ".[test,bench]"
	$(PY) bench/bones.py

clean:
	rm -rf $(DEMO_OUT) .pytest_cache
