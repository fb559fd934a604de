# Two commands on a fresh machine: `make run` (set up, then run the main job) and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup run test test-all clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q -e '.[test]'
	touch $@

# The main job. Until the flying issue lands it draws the default scene (setting 2, seed 3) from 70 m.
run: setup
	mkdir -p runs
	$(VENV)/bin/uavsearch scene show --seed 3 --setting 2 --out runs/scene_show.png

test: setup
	$(PY) -m pytest -q

test-all: setup
	$(PY) -m pytest -q -m ''

clean:
	rm -rf $(VENV) runs .pytest_cache
