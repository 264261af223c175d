# Two entry points for a fresh machine (see README.md):
#   make demo   create .venv, install, and run the main job on the bundled default dataset
#   make test   create .venv, install with the test extras, and run the default test suite
# `make test-slow` runs the reference-quality tests marked `slow`.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
DEMO_OUT ?= demo-output

.PHONY: demo test test-slow venv install install-test clean

$(VENV)/bin/python:
	@py=$$(scripts/find-python.sh) || exit 1; echo "using $$py"; "$$py" -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

install: $(VENV)/bin/python
	$(PY) -m pip install --quiet -e .

install-test: $(VENV)/bin/python
	$(PY) -m pip install --quiet -e ".[test]"

demo: install
	$(VENV)/bin/lmpromp demo --out $(DEMO_OUT) --force

test: install-test
	$(PY) -m pytest -n 2 --dist loadfile -q

test-slow: install-test
	$(PY) -m pytest -q -m slow

# render the teaching notebooks with outputs into docs/notebooks/ (notebooks/README.md)
.PHONY: notebooks
notebooks: install-test
	$(PY) scripts/render_notebooks.py

# regenerate the committed example reports under reports/compare/ (a few minutes each).
# GShape with the default basis (J = 20); the synthetic set (generated with J = 10) and
# GunPoint (L = 50) with J = 10, which keeps their NUTS references within minutes.
.PHONY: reports
reports: install
	$(VENV)/bin/lmpromp compare "lasa:GShape?every=20" --latent-dim 2 --draws 500 --out reports/compare/lasa-gshape --force
	$(VENV)/bin/lmpromp compare "synthetic:latent?L=20&D=2&J=10&V=3&seed=0" --num-basis 10 --latent-dim 3 --draws 500 --out reports/compare/synthetic-latent --force
	$(VENV)/bin/lmpromp compare gunpoint:train --num-basis 10 --latent-dim 2 --draws 500 --out reports/compare/gunpoint --force

# regenerate reports/real-data/: the default settings on every LASA shape, GunPoint and
# synthetic data, seven held-out folds each, with CAVI and the mixture rows (about 10
# minutes on 2 cores), then with NUTS on the same datasets (about 41 minutes; docs/defaults.md)
.PHONY: real-data
real-data: install
	$(VENV)/bin/lmpromp real-data --out reports/real-data --engines cavi --max-folds 7 --mixture-seeds 10 --seed 0 --force
	$(VENV)/bin/lmpromp real-data --out reports/real-data --engines nuts --nuts-datasets all --nuts-folds 7 --mixture-seeds 0 --seed 0 --merge --force

# regenerate reports/timing/: prediction with unknown timing, leave-one-out, seven folds per
# recorded dataset and every demonstration of the synthetic one (synthetic durations, eight
# LASA shapes, GunPoint; linear and aligned phases; about 14 minutes on 2 cores)
.PHONY: timing-report
timing-report: install
	$(VENV)/bin/lmpromp timing --out reports/timing --max-folds 7 --seed 0 --force

clean:
	rm -rf $(VENV) $(DEMO_OUT)
