# fluxmap: reproducible set-up, tests, benchmarks and experiments.
#   make demo   create .venv, install, run the demo pipeline, print where its output is
#   make check-report   open the demo's report in headless Chromium: screenshot, console, 3-D view
#   make demo-rig   the simulated rig: capture-surface (structured light + emission) -> build-T on the
#                   captured surface -> reconstruct -> report; the same frames on the true surface beside
#   make structured-light   structured-light surface capture on the simulated rig, against the truth
#   make test   create .venv if needed, install with test extras, run the test suite
#   make bench  speed ratios measured in one run (slow checks included)
#   make accuracy  issue 8's battery: error, totals, chi^2, lambda, warnings per case x method;
#                  then issue 21's on Monte Carlo phantoms (benchmarks/accuracy_mc.py) and the
#                  body-curvature term against photons leaving spheres and a cylinder
#   make paper-2d | paper-3d | heights   the paper's experiments (pipelines/experiments.mk)
#   make study  issue 24: a simulated study (growing source, 3 days, 2 poses, 2 filters) -> fluxmap study
#   make phantom  issue 21: a turbid box's Monte Carlo photons read as diffuse, then as Lambertian (~5 min)

PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
FLUXMAP = $(VENV)/bin/fluxmap
JOBS   ?= 2

.PHONY: all demo demo-rig structured-light demo-rig-truemesh check-report config-reference accuracy test bench samples figures clean help
all: test

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

install: $(VENV)/.installed

# The demo's artefacts carry a fixed creation time (SOURCE_DATE_EPOCH: the commit's), so that
# every clone makes the same bytes.
DEMO_EPOCH := $(shell git log -1 --format=%ct 2>/dev/null || echo 0)
demo: $(VENV)/.installed
	@echo "== demo 1/4: build-T (the first run after an install also compiles the ray-casting kernels)"
	SOURCE_DATE_EPOCH=$(DEMO_EPOCH) $(FLUXMAP) build-T configs/demo.yaml --jobs $(JOBS)
	@echo "== demo 2/4: simulate"
	SOURCE_DATE_EPOCH=$(DEMO_EPOCH) $(FLUXMAP) simulate configs/demo.yaml --jobs $(JOBS)
	@echo "== demo 3/4: reconstruct"
	SOURCE_DATE_EPOCH=$(DEMO_EPOCH) $(FLUXMAP) reconstruct configs/demo.yaml --jobs $(JOBS)
	@echo "== demo 4/4: report"
	SOURCE_DATE_EPOCH=$(DEMO_EPOCH) $(FLUXMAP) report configs/demo.yaml
	@$(FLUXMAP) summary configs/demo.yaml

# The demo's report in headless Chromium (Debian: apt-get install chromium): a screenshot, no console
# errors, the 3-D view not blank.  Not part of `make test` (CI has no browser).
check-report: $(VENV)/.installed
	@test -f runs/demo/report/index.html || $(MAKE) demo
	$(PY) -m fluxcli.report.browser_check runs/demo/report/index.html runs/demo/report/screenshot.png

# issue 8: realistic, honestly simulated cases x methods (~20 min on 2 cores); then issue 21's Monte Carlo battery (~50 min), then the body's curvature against photons (~2 min)
accuracy: $(VENV)/.installed
	$(PY) benchmarks/accuracy.py --draws 5
	$(PY) benchmarks/accuracy_mc.py
	$(PY) benchmarks/body_curvature_photons.py

demo-rig: $(VENV)/.installed  # issue 12: build-T and reconstruct on the surface capture-surface measured
	@echo "== demo-rig 1/5: capture-surface (structured light, then the emission frames; ~30 s)"
	$(FLUXMAP) capture-surface configs/demo-rig.yaml --resume
	@echo "== demo-rig 2/5: build-T on the captured surface"
	$(FLUXMAP) build-T configs/demo-rig.yaml --jobs $(JOBS)
	@echo "== demo-rig 3/5: reconstruct on the captured surface (each pose's solve says when it ends)"
	$(FLUXMAP) reconstruct configs/demo-rig.yaml --jobs $(JOBS)
	@echo "== demo-rig 4/5: report"
	$(FLUXMAP) report configs/demo-rig.yaml
	@echo "== demo-rig 5/5: the same frames on the true surface, and the totals beside the truth"
	$(MAKE) --no-print-directory demo-rig-truemesh
	$(PY) pipelines/rig_totals.py runs/demo-rig/reconstruction.h5 --against runs/demo-rig-truemesh/reconstruction.h5
	@echo "demo-rig report: $(CURDIR)/runs/demo-rig/report/index.html"

test: $(VENV)/.installed
	$(PY) -m pytest -q

structured-light: $(VENV)/.installed  # issue 12: simulated structured-light capture measured against the truth
	$(PY) pipelines/structured_light.py runs/structured-light

demo-rig-truemesh: $(VENV)/.installed  # demo-rig's frames reconstructed on the TRUE surface (after demo-rig's capture)
	$(FLUXMAP) build-T configs/demo-rig-truemesh.yaml --jobs $(JOBS)
	$(FLUXMAP) reconstruct configs/demo-rig-truemesh.yaml --jobs $(JOBS)

bench: $(VENV)/.installed
	$(PY) -m pytest -q -m slow --benchmark-disable || test $$? -eq 5  # 5: no slow checks collected
	$(PY) benchmarks/run.py  # one table + runs/bench/bench.json (benchmarks/bench_*.py)

samples: $(VENV)/.installed
	$(PY) data-samples/make_samples.py
	$(PY) data-samples/calibration/make_radiometric.py

# docs/config-reference.md from the schema (tests/test_docs.py fails when it is out of date)
config-reference: $(VENV)/.installed
	$(PY) docs/make_config_reference.py

figures: $(VENV)/.installed
	$(PY) docs/make_figures.py

clean:
	rm -rf runs .pytest_cache

help:
	@sed -n '2,14p' Makefile

-include pipelines/*.mk

# issue 21: light carried out of a turbid box by photon Monte Carlo (no emission model in the images),
# reconstructed per pose with subject.emission: diffuse, then the same photons read as Lambertian: each
# summary ends with each pose's total over the truth on the elements it observes (~5 min on 2 cores).
.PHONY: phantom
phantom: $(VENV)/.installed
	$(FLUXMAP) simulate configs/phantom.yaml --jobs $(JOBS)
	$(FLUXMAP) reconstruct configs/phantom.yaml --jobs $(JOBS) --quiet
	@echo "== diffuse (configs/phantom.yaml)"
	@$(FLUXMAP) summary configs/phantom.yaml | grep -E "over the truth|direct ROI sum [0-9]"
	mkdir -p runs/phantom-lambertian && cp runs/phantom/simulation.h5 runs/phantom-lambertian/
	$(FLUXMAP) reconstruct configs/phantom.yaml --set 'subject.emission={model: lambertian}' \
	    --set workdir=../runs/phantom-lambertian --jobs $(JOBS) --quiet
	@echo "== the same photons read as lambertian"
	@$(FLUXMAP) summary configs/phantom.yaml --set 'subject.emission={model: lambertian}' \
	    --set workdir=../runs/phantom-lambertian | grep -E "over the truth"

# issue 26: does the calibration's sigma cover its error?  20 true cameras drawn within the stated sigma,
# reconstructed with the calibrated one (the truth within 2 sigma of the total: counted; ~2 min on 2 cores)
.PHONY: calibration-budget
calibration-budget: $(VENV)/.installed
	$(PY) benchmarks/calibration_budget.py --draws 20

# Calibration sample: fit the camera, draw its report, then reconstruct with it vs the true camera (1 % check).
.PHONY: calibrate-demo
calibrate-demo: $(VENV)/.installed
	$(FLUXMAP) calibrate configs/calibrate.yaml
	$(FLUXMAP) report configs/calibrate.yaml
	$(PY) data-samples/calibration/check_end_to_end.py
