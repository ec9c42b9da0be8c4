# Reproducible experiments: each is build-T -> simulate -> reconstruct -> report, chained
# by their HDF5 artefacts.  A stage whose inputs did not change skips itself, and T comes
# from the content-addressed cache, so editing only reconstruction settings redoes only
# reconstruct.  `make -j2 paper-2d paper-3d heights` runs them side by side.
# Every stage is always called (FORCE): whether it is up to date is the stage's own digest
# (config, inputs, and the code's ALGORITHM_VERSION / SOLVER_VERSION), not a file date, so a
# new solver redoes the reconstructions that an unchanged config would have kept.
FORCE:
.PHONY: FORCE

define experiment
$(1)_DIR := runs/$(1)
runs/$(1)/transfer.h5: configs/$(1).yaml $$(VENV)/.installed FORCE
	$$(FLUXMAP) build-T $$< --jobs $$(JOBS)
runs/$(1)/simulation.h5: configs/$(1).yaml runs/$(1)/transfer.h5 FORCE
	$$(FLUXMAP) simulate $$< --jobs $$(JOBS)
runs/$(1)/reconstruction.h5: configs/$(1).yaml runs/$(1)/simulation.h5 FORCE
	$$(FLUXMAP) reconstruct $$< --jobs $$(JOBS)
runs/$(1)/report/index.html: configs/$(1).yaml runs/$(1)/reconstruction.h5 FORCE
	$$(FLUXMAP) report $$<
$(1): runs/$(1)/report/index.html
	@echo "$(1): report at $$(CURDIR)/runs/$(1)/report/index.html"
.PHONY: $(1)
endef

$(eval $(call experiment,paper-2d))
$(eval $(call experiment,paper-3d))
$(eval $(call experiment,heights))
