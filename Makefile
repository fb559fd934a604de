# Two commands on a fresh machine: `make run` (set up, then run the main job) and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup run test test-all clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q -e '.[test]'
	# MAVProxy for the ground-station test, without its declared dependencies (opencv-python and vtk
	# would clash with opencv-python-headless); what it imports is already here plus pyserial.
	$(PY) -m pip install -q --no-deps mavproxy==1.8.75 pyserial==3.5
	touch $@

# The main job: fly the default search mission (paper setting 2) with the shipped model.
run: setup
	$(VENV)/bin/uavsearch fly

test: setup
	$(PY) -m pytest -q

test-all: setup
	$(PY) -m pytest -q -m ''

clean:
	rm -rf $(VENV) runs .pytest_cache
