# Two commands on a fresh machine: `make run` (set up, then run the main job) and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
DETECTOR_VENV ?= .venv-detector

.PHONY: setup browser run test test-all clean detector-venv

setup: $(VENV)/.installed

# pip prints one line per package it collects and installs (a fresh setup takes about 1.5 minutes,
# results/setup_time.md, measured by tools/bench_setup.py; torch's CPU wheel is the largest part), so the first
# `make run` is never a silent wait.
$(VENV)/.installed: pyproject.toml
	@echo "setup: creating $(VENV) and installing uavsearch with its dependencies (about 1.5 minutes the first time)"
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --progress-bar off --disable-pip-version-check -e '.[test]'
	# MAVProxy for the ground-station test, without its declared dependencies (opencv-python and vtk
	# would clash with opencv-python-headless); what it imports is already here plus pyserial.
	$(PY) -m pip install --progress-bar off --disable-pip-version-check --no-deps mavproxy==1.8.75 pyserial==3.5
	@touch $@
	@echo "setup: done; the command is $(VENV)/bin/uavsearch (or: . $(VENV)/bin/activate)"

# The main job: fly the default search mission (missions/wide.yaml: the learned wide-area policy, 240 s of flight)
# with the shipped models, then the same scene searched by the first view, the best fixed route and the rule.
# `uavsearch fly --mission default` flies the paper's setting 2.
run: setup
	$(VENV)/bin/uavsearch fly

# Headless Chromium for the flight review page's browser test (skipped with a message where it cannot be had).
browser:
	@bash tools/install_browser.sh

# Two processes, one test file each at a time (pytest-xdist): most tests wait on a vehicle process, so two
# cores run the suite in about half the time; a file's module fixtures (one flight shared by its tests) stay whole.
test: setup browser
	$(PY) -m pytest -q -n 2 --dist loadfile

# The slow tests too; the Ray cluster test needs the ray extra.
test-all: setup browser
	$(PY) -m pip install --progress-bar off --disable-pip-version-check -e '.[test,ray]'
	$(PY) -m pytest -q -n 2 --dist loadfile -m ''

# A venv for examples/detector_plugin.py's Faster R-CNN: torchvision needs the torch it was built for (2.14.1, not
# the project's 2.13.0), so uavsearch goes in without its dependencies and those, less torch, are listed here.
detector-venv:
	$(PYTHON) -m venv $(DETECTOR_VENV)
	$(DETECTOR_VENV)/bin/pip install --progress-bar off --disable-pip-version-check torch==2.14.1 torchvision==0.29.1
	$(DETECTOR_VENV)/bin/pip install --progress-bar off --disable-pip-version-check --no-deps -e .
	$(DETECTOR_VENV)/bin/pip install --progress-bar off --disable-pip-version-check 'numpy>=1.26,<3' 'scipy>=1.11' \
		jsbsim==1.3.3 pybullet==3.2.7 pymavlink==2.4.50 mavsdk==4.1.0 gymnasium==1.4.0 'opencv-python-headless>=4.9' \
		'matplotlib>=3.8' 'imageio>=2.34' 'tqdm>=4.66' 'pydantic>=2.6,<3' 'pyyaml>=6' 'plotly>=6,<8' \
		'fsspec>=2024.2' pycocotools==2.0.11
	$(DETECTOR_VENV)/bin/python -c "import torch, torchvision, uavsearch; print(torchvision.ops.nms(torch.tensor([[0., 0., 9., 9.]] * 2), torch.tensor([.9, .8]), .5))"

clean:
	rm -rf $(VENV) runs .pytest_cache
